"""Output folders: a run replaces the previous run's files, a failure leaves the folder as it was, benches write
outside the repository's tracked files by default."""

from __future__ import annotations

from pathlib import Path

import pytest

import volren.bench as bench
import volren.bench.runner as runner
import volren.output as output
from volren.cli import main
from volren.errors import VolrenError

TINY = ("--width", "24", "--height", "16", "--resolution", "64", "--samples", "8", "--light-samples", "4",
        "--light-grid", "8", "--device", "cpu")


def listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else b"<dir>" for p in folder.rglob("*")}


def test_new_run_replaces_old_runs_files_and_keeps_the_rest(tmp_path):
    out = tmp_path / "out"
    assert main(["render", *TINY, "--views", "4", "--save-linear", "--out", str(out)]) == 0
    assert {"view3.png", "view3.npy", "contact.png", "stats.json"} <= set(listing(out))
    (out / "notes.txt").write_text("mine")
    (out / "cloud").mkdir()
    (out / "cloud" / "view0.png").write_bytes(b"a sub-run")
    (out / "view0_error.png").write_bytes(b"a heat map of the old view 0")
    assert main(["render", *TINY, "--views", "mono", "--out", str(out)]) == 0
    assert set(listing(out)) == {"view0.png", "stats.json", "notes.txt", "cloud", "cloud/view0.png"}
    assert (out / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging or trash folder left


def test_failing_render_leaves_folder_as_it_was(tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    assert main(["render", *TINY, "--views", "stereo", "--out", str(out)]) == 0
    before = listing(out)

    def fail(*args, **kwargs):
        raise VolrenError("disk full")

    monkeypatch.setattr(output, "write_stats", fail)  # fails after every image of the new run is written
    assert main(["render", *TINY, "--views", "mono", "--out", str(out)]) == 2
    assert "disk full" in capsys.readouterr().err
    assert listing(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    new = tmp_path / "a" / "b" / "run"
    assert main(["render", *TINY, "--views", "mono", "--out", str(new)]) == 2
    assert not (tmp_path / "a").exists()  # the parents it made are gone too


def test_run_output_moves_in_only_when_complete(tmp_path):
    out = tmp_path / "run"
    with output.run_output(out) as staging:
        assert staging.parent == tmp_path and staging != out
        (staging / "view0.png").write_bytes(b"x")
        assert not out.exists()
    assert listing(out) == {"view0.png": b"x"}
    with pytest.raises(RuntimeError), output.run_output(out) as staging:
        (staging / "view1.png").write_bytes(b"y")
        raise RuntimeError
    assert listing(out) == {"view0.png": b"x"}
    (tmp_path / "file").write_text("")
    with pytest.raises(VolrenError, match=r"'.*file' is a file"), output.run_output(tmp_path / "file"):
        pass


def test_bench_writes_to_out_bench_by_default(tmp_path, monkeypatch):
    suite = bench.Suite("tiny", "a one-row suite", lambda quick, device: {"rows": [{"n": 1}],
                                                                        "columns": [("n", "n", "d")]})
    monkeypatch.setattr(runner, "all_suites", lambda: {"tiny": suite})
    monkeypatch.chdir(tmp_path)
    assert Path("out/bench") == bench.DEFAULT_OUT
    assert main(["bench", "tiny", "--quick", "--device", "cpu"]) == 0
    assert sorted(listing(tmp_path)) == ["out", "out/bench", "out/bench/tiny-cpu-quick.json",
                                         "out/bench/tiny-cpu-quick.md"]
    assert "| 1 |" in (tmp_path / "out/bench/tiny-cpu-quick.md").read_text()
