// The run report's scripts (msmem_core/run/report/page.py puts each section where it belongs in report.html).
// A line "//= NAME: what it does" starts the section NAME; "{plot_id}" is the id plotly gives the plot's <div>.

//= error-hook: in <head>, first: collects uncaught errors and console errors for the status line
window.msmemErrors = [];
window.addEventListener('error', function (e) { window.msmemErrors.push(String(e.message)); });
(function () { var orig = console.error; console.error = function () {
  window.msmemErrors.push(Array.prototype.join.call(arguments, ' ')); return orig.apply(console, arguments); }; })();

//= plot-done: in <head>: counts the drawn plots and writes the status line (the headless-browser test reads it)
function msmemPlotDone() {
  var el = document.getElementById('msmem-status');
  var plots = document.querySelectorAll('.js-plotly-plot');
  var drawn = 0;
  plots.forEach(function (p) {  // a 3-D scene without WebGL shows plotly's .no-webgl notice instead
    if (p._fullLayout && p.dataset.msmemRendered === '1' && !p.querySelector('.no-webgl')) { drawn += 1; }
  });
  el.dataset.plots = String(drawn);
  el.dataset.errors = String(window.msmemErrors.length);
  el.textContent = drawn + ' of ' + el.dataset.expected + ' plots drawn, ' + window.msmemErrors.length + ' errors'
    + (window.msmemErrors.length ? ': ' + window.msmemErrors.join(' | ') : '');
  document.title = 'msmem report: ' + el.dataset.steps + ' steps, ' + drawn + ' plots';
}
window.addEventListener('load', function () { msmemPlotDone(); setTimeout(msmemPlotDone, 1000); });

//= sync-cameras: after the 3-D plot is drawn: the belief's and the ground truth's scenes turn together
var gd = document.getElementById('{plot_id}');
gd.dataset.msmemRendered = '1';
var syncing = false;
gd.on('plotly_relayout', function (ev) {
  if (syncing) { return; }
  var out = {};
  if (ev['scene.camera']) { out['scene2.camera'] = ev['scene.camera']; }
  if (ev['scene2.camera']) { out['scene.camera'] = ev['scene2.camera']; }
  if (Object.keys(out).length) { syncing = true; Plotly.relayout(gd, out).then(function () { syncing = false; }); }
});
msmemPlotDone();

//= metrics-drawn: after the metrics plot is drawn
document.getElementById('{plot_id}').dataset.msmemRendered = '1'; msmemPlotDone();
