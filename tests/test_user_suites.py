"""Benching your own scenes: a folder of scene files or a suite file works as a shipped suite does
(resume and fingerprints included); bad suites and an impossible hardness check say what to change."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from msmem_core.errors import UserError
from msmem_core.run.bench import suite_scenes
from msmem_core.world.scenegen import SceneGenConfig, generate_scene

ROOT = Path(__file__).resolve().parents[1]
HARD25 = ROOT / "msmem_core" / "suites" / "hard25"
MSMEM = [str(Path(sys.executable).with_name("msmem"))]


def _folder(tmp_path: Path) -> Path:
    d = tmp_path / "my-scenes"
    d.mkdir()
    for i in (3, 1):
        shutil.copy(HARD25 / f"scene_{i:02d}.json", d / f"shelf_{i}.json")
    return d


def test_a_folder_and_a_suite_file_give_the_scenes_in_order(tmp_path: Path) -> None:
    d = _folder(tmp_path)
    shipped = suite_scenes("hard25")
    assert suite_scenes(str(d)) == [shipped[1], shipped[3]]  # by file name: shelf_1, shelf_3
    f = d / "suite.yaml"
    f.write_text("scenes: [shelf_3.json, shelf_1.json]\n")
    assert suite_scenes(str(f)) == [shipped[3], shipped[1]]  # as the file lists them


@pytest.mark.parametrize(("make", "message"), [
    (lambda d: str(d / "nowhere"), "not a shipped suite"),
    (lambda d: (d / "empty").mkdir() or str(d / "empty"), "holds no scene file"),
    (lambda d: (d / "s.yaml").write_text("- a.json\n") and str(d / "s.yaml"), "under `scenes:`"),
    (lambda d: (d / "s.yaml").write_text("scenes: [missing.json]\n") and str(d / "s.yaml"),
     "missing.json does not exist"),
    (lambda d: (d / "bad").mkdir() or ((d / "bad" / "x.json").write_text('{"objects": 3}') and str(d / "bad")),
     "x.json"),
])
def test_a_bad_suite_is_one_line_naming_what_is_wrong(tmp_path: Path, make, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(UserError, match=message):
        suite_scenes(make(tmp_path))


@pytest.mark.slow  # an end-to-end run or a benchmark: the slow suite (CI) runs it
def test_bench_runs_a_folder_of_scenes_and_resumes(tmp_path: Path) -> None:
    d = _folder(tmp_path)
    out = tmp_path / "bench"
    cmd = [*MSMEM, "bench", "--methods", "view-only", "--suite", str(d), "--steps", "2", "--workers", "1",
           "--out", str(out)]
    first = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    eps = sorted((out / "episodes").glob("*.json"))
    assert [p.name for p in eps] == ["view-only__scene00.json", "view-only__scene01.json"]
    assert json.loads(eps[0].read_text())["fingerprint"]["suite"] == str(d)
    mtimes = [p.stat().st_mtime_ns for p in eps]
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
    assert again.returncode == 0, again.stderr[-2000:]
    assert [p.stat().st_mtime_ns for p in eps] == mtimes  # resumed: nothing rerun


@pytest.mark.slow  # an end-to-end run or a benchmark: the slow suite (CI) runs it
def test_an_impossible_hardness_check_says_how_hard_the_best_attempt_was(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(UserError, match=r"no attempt got as far as counting .* 3 were screened out.* min_hidden,"):
        generate_scene(0, SceneGenConfig(min_hidden=30, max_tries=3))
    # attempts that pass the screen and are counted: the message names the best count and the setting
    from msmem_core.world import scenegen

    counts = iter([1, 3, 2])
    monkeypatch.setattr(scenegen, "_may_be_hard", lambda *a: True)
    monkeypatch.setattr(scenegen, "_count_hidden", lambda *a: next(counts))
    with pytest.raises(UserError, match=r"the best attempt hid 3; .*min_hidden \(to 3 or less to accept the best\)"):
        generate_scene(1, SceneGenConfig(min_hidden=30, max_tries=3))
