"""What the README promises when training is stopped or killed, checked on real processes.

- Ctrl-C / SIGTERM: the run stops after the current step and writes a final checkpoint even when no
  periodic checkpoint is due; a second Ctrl-C aborts without one.
- ``kill -9`` inside the atomic write of a checkpoint or of its ``latest`` pointer: the previous
  complete checkpoint is what readers get, and ``--resume`` ends at the very weights of a run that
  was never killed.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from relocdepth import checkpoint as ckpt_io
from relocdepth.errors import UserError

torch.set_num_threads(1)

# Tiny and fast: 64x64 input, one triplet per step, random init, no loader workers.
FAST = ["--size", "64x64", "--batch-size", "1", "--pretrained", "none", "--workers", "0",
        "--no-progress", "--log-every", "1"]
NEVER = "100000"  # a --checkpoint-every / --max-steps no test run reaches
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
TIMEOUT = 300.0


class _Proc:
    """A `reloc train` subprocess whose stdout and stderr are collected line by line as it runs."""

    def __init__(self, cmd: list[str]) -> None:
        self.p = subprocess.Popen(cmd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.out: list[str] = []
        self.err: list[str] = []
        self._readers = [threading.Thread(target=self._read, args=(s, dest), daemon=True)
                         for s, dest in ((self.p.stdout, self.out), (self.p.stderr, self.err))]
        for t in self._readers:
            t.start()

    @staticmethod
    def _read(stream, dest: list[str]) -> None:
        dest.extend(stream)  # line by line, as the process writes

    def stderr(self) -> str:
        return "".join(self.err)

    def wait_for(self, pred, what: str) -> None:
        t0 = time.time()
        while not pred():
            assert self.p.poll() is None, f"exited {self.p.returncode} before {what}:\n{self.stderr()[-3000:]}"
            assert time.time() - t0 < TIMEOUT, f"timed out waiting for {what}"
            time.sleep(0.05)

    def finish(self) -> tuple[int, str, str]:
        """Wait for the exit; (return code, stdout, stderr)."""
        self.p.wait(timeout=TIMEOUT)
        for t in self._readers:
            t.join(timeout=30)
        return self.p.returncode, "".join(self.out), self.stderr()


def _train_cmd(shards: Path, run: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "relocdepth.cli", "train", str(shards), "-o", str(run), *FAST, *extra]


def _log(run: Path) -> list[dict]:
    """The run's log records so far (complete lines only: the trainer may be writing one)."""
    p = run / "logs" / "train.jsonl"
    return [json.loads(x) for x in p.read_text().split("\n")[:-1]] if p.is_file() else []


def _logged_steps(run: Path) -> list[int]:
    return [r["step"] for r in _log(run) if r["kind"] == "step"]


def _files(run: Path) -> list[str]:
    d = run / "checkpoints"
    return sorted(p.name for p in d.iterdir()) if d.is_dir() else []


# -- Ctrl-C and SIGTERM ------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_stop_signal_writes_a_final_checkpoint(synth_shards: Path, tmp_path: Path, sig: int) -> None:
    run = tmp_path / "run"
    proc = _Proc(_train_cmd(synth_shards, run, "--checkpoint-every", NEVER, "--max-steps", NEVER))
    proc.wait_for(lambda: len(_logged_steps(run)) >= 1, "the first step")
    assert ckpt_io.list_checkpoints(run) == []  # no periodic checkpoint is due for 100000 steps
    proc.p.send_signal(sig)
    rc, out, err = proc.finish()
    assert rc == 130, err[-3000:]
    assert err.count("stop requested") == 1
    # One checkpoint, of the step the run stopped at: the steps it trained are all in it.
    steps = _logged_steps(run)
    stop = [r for r in _log(run) if r.get("event") == "stop"]
    assert len(stop) == 1 and stop[0]["reason"] == "interrupted"
    last = stop[0]["step"]
    assert last == steps[-1] >= 1 and last < int(NEVER)
    assert _files(run) == [ckpt_io.checkpoint_name(last), "latest"]
    assert f"stop: interrupted); checkpoint {run / 'checkpoints' / ckpt_io.checkpoint_name(last)}" in out
    nets, meta = ckpt_io.load_for_inference(run)
    assert meta["step"] == last
    # It holds the weights the process ended with (the digest it logs last), not older ones.
    from relocdepth.distributed import parameter_digest

    logged = re.findall(r"rank 0: final parameters sha256 ([0-9a-f]{64})", err)
    assert logged == [parameter_digest(nets)]


# Runs `reloc train` with the checkpoint writer held back: before writing a checkpoint it says so on
# stderr and waits, so a test can deliver a signal while the trainer is finishing (on a loaded machine
# a tiny run may otherwise finish its step and checkpoint before the test gets to send it).
_WAITING_WRITER = '''
import sys, time
from pathlib import Path

import relocdepth.checkpoint as C

real = C.atomic_write


def atomic_write(path, write):
    if Path(path).name.startswith("ckpt-"):
        print("checkpoint writer waiting", file=sys.stderr, flush=True)
        time.sleep(120)
    return real(path, write)


C.atomic_write = atomic_write
from relocdepth.cli.main import main

main(sys.argv[1:])
'''


@pytest.mark.slow
def test_second_ctrl_c_aborts_without_a_checkpoint(synth_shards: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    script = tmp_path / "waiting_writer.py"
    script.write_text(_WAITING_WRITER)
    cmd = [sys.executable, str(script), *_train_cmd(synth_shards, run, "--checkpoint-every", NEVER,
                                                    "--max-steps", NEVER)[3:]]
    proc = _Proc(cmd)
    proc.wait_for(lambda: len(_logged_steps(run)) >= 1, "the first step")
    proc.p.send_signal(signal.SIGINT)
    # The second one once the first was handled (two signals before Python runs its handler would
    # count as one), while the trainer is finishing: about to write its final checkpoint.
    proc.wait_for(lambda: "stop requested" in proc.stderr(), "the first signal's message")
    proc.wait_for(lambda: "checkpoint writer waiting" in proc.stderr(), "the final checkpoint")
    proc.p.send_signal(signal.SIGINT)
    rc, out, err = proc.finish()
    # The exit code is the one of an interrupted run (130) either way; what differs is that the
    # aborted run neither finishes (no summary line, no stop event) nor writes its checkpoint.
    assert rc == 130, err[-3000:]
    assert "trained " not in out
    assert [n for n in _files(run) if n != "latest"] == []  # no final checkpoint, no temp file ...
    assert not any(r.get("event") == "stop" for r in _log(run))  # ... and no clean stop


# -- kill -9 inside an atomic write -------------------------------------------------------------------
# Runs `reloc train` with the atomic writer wrapped: on the FAULT_NTH write of a file named FAULT_FILE
# it serialises the real content, writes the first half of it into the temp file, syncs it, and
# SIGKILLs its own process (what a power cut or the OOM killer does mid-write).
_KILLING_WRITER = '''
import io, json, os, signal, sys
from pathlib import Path

import relocdepth.checkpoint as C
import relocdepth.fileio as F

name, nth, report = os.environ["FAULT_FILE"], int(os.environ["FAULT_NTH"]), os.environ["FAULT_REPORT"]
real = F.atomic_write
seen = {"n": 0}


def atomic_write(path, write):
    if Path(path).name != name:
        return real(path, write)
    seen["n"] += 1
    if seen["n"] < nth:
        return real(path, write)
    buf = io.BytesIO()
    write(buf)
    data = buf.getvalue()

    def half_then_die(f):
        f.write(data[: len(data) // 2])
        f.flush()
        os.fsync(f.fileno())
        Path(report).write_text(json.dumps({"full": len(data), "written": len(data) // 2}))
        os.kill(os.getpid(), signal.SIGKILL)

    return real(path, half_then_die)


C.atomic_write = atomic_write
F.atomic_write = atomic_write
from relocdepth.cli.main import main

main(sys.argv[1:])
'''


def _cli(*args: str) -> None:
    from relocdepth.cli.main import app
    from typer.testing import CliRunner

    res = CliRunner().invoke(app, list(args))
    assert res.exit_code == 0, res.output[-3000:]


@pytest.fixture(scope="module")
def straight3(synth_shards: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, torch.Tensor]:
    """The weights after 3 steps of a run that nobody killed."""
    run = tmp_path_factory.mktemp("straight") / "run"
    _cli("train", str(synth_shards), "-o", str(run), *FAST, "--checkpoint-every", NEVER, "--max-steps", "3")
    return torch.load(ckpt_io.latest_checkpoint(run), weights_only=True)["model"]


@pytest.mark.slow
@pytest.mark.parametrize(("fault_file", "nth", "survivor"), [
    ("ckpt-00000002.pt", 1, 1),  # killed while writing checkpoint 2's temp file
    ("latest", 2, 2),  # killed while writing the pointer to checkpoint 2 (after its rename)
], ids=["in-checkpoint", "in-pointer"])
def test_kill9_inside_the_atomic_write(synth_shards: Path, tmp_path: Path, straight3: dict[str, torch.Tensor],
                                       fault_file: str, nth: int, survivor: int) -> None:
    run, report = tmp_path / "run", tmp_path / "fault.json"
    script = tmp_path / "killing_writer.py"
    script.write_text(_KILLING_WRITER)
    cmd = [sys.executable, str(script), "train", str(synth_shards), "-o", str(run), *FAST,
           "--checkpoint-every", "1", "--max-steps", "3"]
    env = {**ENV, "FAULT_FILE": fault_file, "FAULT_NTH": str(nth), "FAULT_REPORT": str(report)}
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=TIMEOUT, check=False)
    assert res.returncode == -signal.SIGKILL, res.stderr[-3000:]
    # The kill landed inside the write: a half-written temp file is on disk, under a temp name.
    fault = json.loads(report.read_text())
    d = run / "checkpoints"
    temps = list(d.glob(f".{fault_file}.*.tmp"))
    assert len(temps) == 1 and temps[0].stat().st_size == fault["written"] < fault["full"]
    if fault_file.endswith(".pt"):
        with pytest.raises(UserError, match="not a readable relocdepth checkpoint"):
            ckpt_io.load_checkpoint(temps[0])  # what a reader of that file would meet
    complete = [p.name for p in ckpt_io.list_checkpoints(run)]
    assert complete == [ckpt_io.checkpoint_name(s) for s in range(1, survivor + 1)]
    pointer = json.loads((d / "latest").read_text())
    assert pointer["checkpoint"] == ckpt_io.checkpoint_name(1)  # stale in the pointer case
    # Readers get the newest complete checkpoint, and it loads.
    assert ckpt_io.latest_checkpoint(run) == d / ckpt_io.checkpoint_name(survivor)
    _, meta = ckpt_io.load_for_inference(run)
    assert meta["step"] == survivor
    # --resume continues from it and ends where a run that was never killed ends.
    _cli("train", str(synth_shards), "-o", str(run), *FAST, "--checkpoint-every", NEVER, "--max-steps", "3",
         "--resume")
    assert not list(d.glob(".*.tmp"))  # the dead writer's temp file (checkpoint or pointer) is cleaned up
    final = torch.load(ckpt_io.latest_checkpoint(run), weights_only=True)
    assert final["meta"]["step"] == 3
    resumed = [r for r in _log(run) if r.get("event") == "resume"]
    assert len(resumed) == 1 and resumed[0]["step"] == survivor
    w = final["model"]
    assert w.keys() == straight3.keys() and all(torch.equal(w[k], straight3[k]) for k in w)
