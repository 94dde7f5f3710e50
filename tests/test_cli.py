"""The CLI's shared surface: --version, choices in --help, the one --device grammar, exit codes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from relocdepth.cli.main import app, main
from typer.testing import CliRunner

import relocdepth
from relocdepth.distributed import check_device, pick_device
from relocdepth.errors import TrainingDiverged, UserError


@pytest.fixture(autouse=True)
def keep_logging():
    """main() sets up logging for a process; put back the test session's."""
    import logging

    root = logging.getLogger()
    saved = (root.level, list(root.handlers))
    yield
    root.handlers[:] = saved[1]
    root.setLevel(saved[0])


def invoke(*args: str):
    return CliRunner().invoke(app, list(args))


def test_version() -> None:
    res = invoke("--version")
    assert res.exit_code == 0 and res.stdout.strip() == f"relocdepth {relocdepth.__version__}"
    out = subprocess.run([sys.executable, "-m", "relocdepth.cli", "--version"],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0 and out.stdout.strip() == f"relocdepth {relocdepth.__version__}"


@pytest.mark.parametrize("command", ["train", "localize", "evaluate"])
def test_help_lists_choices_and_one_device_grammar(command: str) -> None:
    res = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    text = " ".join(res.stdout.split())
    assert "auto|cpu|cuda|cuda:N" in text
    if command == "localize":
        assert "json|tum" in text


@pytest.mark.parametrize(("text", "want"), [
    ("auto", "auto"), ("cpu", "cpu"), ("cuda", "cuda"), ("cuda:1", "cuda:1"), (" CUDA:0 ", "cuda:0"),
])
def test_device_grammar_accepts(text: str, want: str) -> None:
    assert check_device(text) == want


@pytest.mark.parametrize("text", ["gpu", "cuda:", "cuda:x", "cpu:0", "mps", "", "cuda:-1"])
def test_device_grammar_refuses(text: str) -> None:
    with pytest.raises(UserError, match=r"--device must be one of auto, cpu, cuda, cuda:N"):
        check_device(text)


def test_device_resolution() -> None:
    import torch

    assert pick_device("cpu") == torch.device("cpu")
    auto = pick_device("auto")
    assert auto.type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        for name in ("cuda", "cuda:0"):
            with pytest.raises(UserError, match="sees no CUDA GPU"):
                pick_device(name)
    else:
        assert pick_device("cuda:0") == torch.device("cuda", 0)
        with pytest.raises(UserError, match="CUDA GPU"):
            pick_device(f"cuda:{torch.cuda.device_count()}")


def test_bad_device_is_one_line_before_anything_is_written(tmp_path: Path) -> None:
    runs = {
        "train": ("train", str(tmp_path / "shards"), "-o", str(tmp_path / "run")),
        "localize": ("localize", str(tmp_path / "img.png"), "-o", str(tmp_path / "poses.jsonl")),
        "evaluate": ("evaluate", str(tmp_path / "shards"), "-o", str(tmp_path / "report.json")),
    }
    (tmp_path / "img.png").write_bytes(b"")
    for args in runs.values():
        res = invoke(*args, "--device", "gpu")
        assert res.exit_code == 2, res.output
        lines = res.output.strip().splitlines()
        want = "error: --device must be one of auto, cpu, cuda, cuda:N (N: a GPU index), not 'gpu'"
        assert lines == [want]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img.png"]


# -- exit codes: 0 ok, 1 a bug, 2 bad input, 3 diverged, 130 interrupted ----------------------------
def _main_exit(argv: list[str]) -> int:
    with pytest.raises(SystemExit) as e:
        main(argv)
    return int(e.value.code or 0)


def test_exit_codes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    import relocdepth.localize
    import relocdepth.train

    assert _main_exit(["--version"]) == 0
    assert _main_exit(["localize", str(tmp_path / "missing.png")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("error: input ")
    assert _main_exit(["localize", "--no-such-option"]) == 2  # usage errors are bad input too

    def diverge(*args, **kwargs):
        raise TrainingDiverged("training diverged: 20 non-finite losses in a row at step 7")

    monkeypatch.setattr(relocdepth.train, "train", diverge)
    assert _main_exit(["train", str(tmp_path), "-o", str(tmp_path / "run")]) == 3
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "error: training diverged: 20 non-finite losses in a row at step 7")
    res = invoke("train", str(tmp_path), "-o", str(tmp_path / "run"))  # the decorator, same code
    assert res.exit_code == 3 and res.output.strip().startswith("error: training diverged")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(relocdepth.localize, "localize", interrupted)
    assert _main_exit(["localize", str(tmp_path)]) == 130

    def bug(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(relocdepth.localize, "localize", bug)
    with pytest.raises(RuntimeError, match="a bug"):  # Python prints the traceback, exits 1
        main(["localize", str(tmp_path)])
