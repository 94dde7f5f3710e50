"""Progress without a terminal: plain lines from training, ingest, evaluate and localize; image
summaries for TensorBoard; logging setup (rich on a terminal, rank 0 at INFO)."""

from __future__ import annotations

import io
import logging
import re
from pathlib import Path

import numpy as np
import pytest
from relocdepth.cli.main import app, setup_logging
from typer.testing import CliRunner

from relocdepth import progress as P
from relocdepth.errors import UserError
from relocdepth.trainlog import TrainLog


class Clock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(P.time, "monotonic", c)
    return c


def test_plain_progress_prints_every_few_seconds_with_rate_and_eta(clock: Clock) -> None:
    out = io.StringIO()
    with P.PlainProgress("ingest", "frames", every_s=5.0, stream=out) as bar:
        task = bar.add_task("seq-01", total=100)
        for _ in range(10):  # 10 frames per second
            clock.t += 1.0
            bar.update(task, advance=10)
    lines = out.getvalue().splitlines()
    # one line at 5 s, one at 10 s (the last update) and none after: nothing new since
    assert lines == [
        "ingest seq-01: 50/100 frames (50%), 10.0 frames/s, ETA 0:00:05",
        "ingest seq-01: 100/100 frames (100%), 10.0 frames/s, ETA 0:00:00",
    ]


def test_plain_progress_final_line_and_unknown_total(clock: Clock) -> None:
    out = io.StringIO()
    bar = P.PlainProgress("localize", "images", every_s=5.0, stream=out)
    bar.start()
    task = bar.add_task("", total=None)
    clock.t += 2.0
    bar.advance(task, 3)
    assert out.getvalue() == ""  # under 5 s: quiet
    bar.stop()
    assert out.getvalue() == "localize: 3 images, 1.5 images/s, done in 0:00:02\n"


def test_progress_bar_is_plain_without_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    from rich.progress import Progress

    monkeypatch.setattr(P, "stderr_is_terminal", lambda: False)
    assert isinstance(P.progress_bar("evaluate"), P.PlainProgress)
    monkeypatch.setattr(P, "stderr_is_terminal", lambda: True)
    bar = P.progress_bar("evaluate")
    assert isinstance(bar, Progress) and bar.console is P.stderr_console()


def test_trainlog_plain_lines_every_log_every_steps(tmp_path: Path, clock: Clock) -> None:
    out = io.StringIO()
    tl = TrainLog(tmp_path, progress=True, total_steps=40, start_step=10, epochs=4,
                  log_every=10, plain=True, stream=out)
    for step in range(11, 41):
        clock.t += 0.5  # 2 steps/s
        tl.tick(step, epoch=(step - 1) // 10, loss=1.0 / step, rate=12.0)
    tl.close()
    lines = out.getvalue().splitlines()
    assert lines == [
        "train: step 20/40, epoch 2/4, loss 0.0500, 12.0 triplets/s, ETA 0:00:10",
        "train: step 30/40, epoch 3/4, loss 0.0333, 12.0 triplets/s, ETA 0:00:05",
        "train: step 40/40, epoch 4/4, loss 0.0250, 12.0 triplets/s, ETA 0:00:00",
    ]


def test_trainlog_eta_is_capped_by_the_wall_clock_budget(tmp_path: Path, clock: Clock) -> None:
    out = io.StringIO()
    tl = TrainLog(tmp_path, progress=True, total_steps=1000, epochs=4, log_every=10, plain=True, stream=out,
                  max_seconds=12.0)
    for step in range(1, 21):
        clock.t += 0.5  # 2 steps/s: 990 steps left would take 495 s, but the budget ends at 12 s
        tl.tick(step, epoch=0, loss=0.5, rate=12.0)
    tl.close()
    assert [line.rsplit("ETA ", 1)[1] for line in out.getvalue().splitlines()] == ["0:00:07", "0:00:02"]


def test_trainlog_other_ranks_print_nothing(clock: Clock) -> None:
    out = io.StringIO()
    tl = TrainLog(None, progress=True, total_steps=5, log_every=1, plain=True, stream=out)
    for step in range(1, 6):
        tl.tick(step, 0, 0.5, 1.0)
    assert out.getvalue() == ""


class FakeWriter:
    def __init__(self) -> None:
        self.images: list[tuple[str, np.ndarray, int, str]] = []

    def add_image(self, tag: str, img: np.ndarray, step: int, dataformats: str) -> None:
        self.images.append((tag, np.asarray(img), step, dataformats))

    def close(self) -> None:
        pass


def test_trainlog_images_for_tensorboard(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    tl = TrainLog(tmp_path, images_every=200)
    tl.images(200, {"depth": np.ones((6, 8))})  # no TensorBoard: nothing happens, no error
    tl._tb = FakeWriter()  # stands in for TensorBoard's SummaryWriter
    assert [s for s in range(1, 1001) if tl.wants_images(s)] == [200, 400, 600, 800, 1000]
    depth = np.tile(np.linspace(1.0, 4.0, 8), (6, 1))  # near on the left
    warped = torch.rand(3, 6, 8)
    tl.images(400, {"depth": depth, "warped_target": warped,
                    "target": (np.ones((3, 6, 8)) * 255).astype(np.uint8)})
    (t1, d, s1, f1), (t2, w, s2, f2), (_, u, _, _) = tl._tb.images
    assert (t1, s1, f1, d.shape, d.dtype) == ("depth", 400, "HWC", (6, 8, 3), np.uint8)
    assert d[:, 0].sum() > d[:, -1].sum()  # near is bright
    assert (t2, s2, f2, w.shape) == ("warped_target", 400, "CHW", (3, 6, 8))
    np.testing.assert_allclose(w, warped.numpy(), atol=1e-6)
    np.testing.assert_allclose(u, 1.0)  # uint8 scaled to [0, 1]
    with pytest.raises(ValueError, match="want"):
        tl.images(600, {"bad": np.ones((2, 6, 8))})
    tl._tb = None
    tl.close()


@pytest.mark.slow
def test_reloc_train_without_terminal_prints_plain_lines(synth_shards: Path, tmp_path: Path) -> None:
    res = CliRunner().invoke(app, [
        "train", str(synth_shards), "-o", str(tmp_path / "run"), "--size", "128x96",
        "--batch-size", "1", "--max-steps", "4", "--log-every", "2", "--pretrained", "none",
        "--workers", "0", "--window", "3", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("train: step")]
    assert [ln.split(",")[0] for ln in lines] == ["train: step 2/4", "train: step 4/4"], res.stderr
    assert all(re.search(r"loss \d+\.\d{4}, [\d.]+ triplets/s, ETA \d+:\d\d:\d\d$", ln) for ln in lines)


def test_ingest_without_terminal_prints_plain_lines(
    synth_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(P, "PLAIN_EVERY_S", 0.0)
    res = CliRunner().invoke(app, ["ingest", str(synth_scene), "-o", str(tmp_path / "shards")])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("ingest seq-")]
    assert lines and re.fullmatch(r"ingest seq-\d\d: \d+/\d+ frames \(\d+%\), .*", lines[0]), res.stderr
    assert "\x1b[" not in res.stderr  # no terminal control codes in a log file


def test_logging_rank_and_handler(monkeypatch: pytest.MonkeyPatch) -> None:
    from rich.logging import RichHandler

    root = logging.getLogger()
    saved = (root.level, list(root.handlers))
    try:
        monkeypatch.setattr(P, "stderr_is_terminal", lambda: False)
        monkeypatch.setenv("RANK", "1")
        setup_logging()
        assert root.level == logging.WARNING
        assert len(root.handlers) == 1 and not isinstance(root.handlers[0], RichHandler)
        assert "[rank 1]" in root.handlers[0].formatter._fmt
        monkeypatch.setenv("RELOCDEPTH_LOG_LEVEL", "info")  # every rank, on request
        setup_logging()
        assert root.level == logging.INFO
        monkeypatch.setenv("RELOCDEPTH_LOG_LEVEL", "loud")
        with pytest.raises(UserError, match="RELOCDEPTH_LOG_LEVEL=LOUD is not a logging level"):
            setup_logging()
        monkeypatch.delenv("RELOCDEPTH_LOG_LEVEL")
        monkeypatch.setenv("RANK", "0")
        monkeypatch.setattr(P, "stderr_is_terminal", lambda: True)
        setup_logging()
        assert root.level == logging.INFO
        assert len(root.handlers) == 1 and isinstance(root.handlers[0], RichHandler)
        assert root.handlers[0].console is P.stderr_console()  # the progress bars' console
    finally:
        root.handlers[:] = saved[1]
        root.setLevel(saved[0])
