"""Speed benchmarks (`msmem perf ...`): IG sweep, one full MSAS decision. (`msmem perf push` is the push
plugin's: `msmem_push.perf`.)"""
