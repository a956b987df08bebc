"""A batch says, per photo, which focus and blur it chose (the issue: a batch did not say it)."""

from __future__ import annotations

import io
import sys

import numpy as np
import pytest

import bokehray as br
from bokehray.app.batch import photo_line
from bokehray.app.cli import main


def test_batch_prints_one_line_per_photo_with_its_focus_and_amount(tmp_path, capsys):
    rng = np.random.default_rng(7)
    for i in range(2):
        d = np.full((40, 56), 0.2, np.float32)
        d[10:30, 15 + 10 * i:40 + 10 * i] = 0.8 - 0.1 * i  # a near subject, a different one per photo
        br.write_image(tmp_path / "photos" / f"p{i}.png", (rng.random((40, 56, 3)) * 0.8).astype(np.float32))
        br.write_disparity(tmp_path / "maps" / f"p{i}.png", d)
    code = main(["render", str(tmp_path / "photos"), "--disparity", str(tmp_path / "maps"), "-o",
                 str(tmp_path / "out"), "--workers", "1"])
    out = capsys.readouterr().out
    assert code == 0
    lines = sorted(x for x in out.splitlines() if " -> " in x and "focus d_f" in x)
    assert len(lines) == 2, out
    for i, line in enumerate(lines):
        assert line.startswith(f"p{i}.png -> p{i}.png: focus d_f = {0.8 - 0.1 * i:.3f} (the subject around pixel")
        assert line.endswith("amount 50 (K = 2.1 px)")
    # --quiet prints none of them
    code = main(["render", str(tmp_path / "photos"), "--disparity", str(tmp_path / "maps"), "-o",
                 str(tmp_path / "out2"), "--workers", "1", "--quiet"])
    assert code == 0 and "focus d_f" not in capsys.readouterr().out


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_batch_draws_no_bar_frames_when_stderr_is_no_terminal(tmp_path, capsys, monkeypatch):
    """Regression: the batch's tqdm bar redrew itself with carriage returns into a stderr redirected to a file or a CI
    log. Off a terminal there is no bar now (the per-photo lines on stdout say the progress); on one it is drawn."""
    rng = np.random.default_rng(8)
    for i in range(3):
        br.write_image(tmp_path / "photos" / f"p{i}.png", (rng.random((24, 32, 3)) * 0.8).astype(np.float32))
        br.write_disparity(tmp_path / "maps" / f"p{i}.png", rng.random((24, 32)).astype(np.float32))
    argv = ["render", str(tmp_path / "photos"), "--disparity", str(tmp_path / "maps"), "--workers", "1",
            "--blur", "3", "--focus", "0.5", "-o"]
    code = main([*argv, str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert code == 0 and captured.out.count(": focus d_f = ") == 3, captured
    assert "\r" not in captured.err and "\r" not in captured.out, repr(captured.err)
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main([*argv, str(tmp_path / "out2")]) == 0
    assert "\r" in terminal.getvalue() and "render" in terminal.getvalue()


def test_photo_line_of_a_given_blur_and_metric_focus():
    line = photo_line("/a/b/x.jpg", {"output": "/o/x.jpg", "focus_disparity": 0.5, "focus": "--focus-at",
                                     "focus_m": 2.5, "amount": None, "k_px": 12.25})
    assert line == "x.jpg -> x.jpg: focus d_f = 0.500 (--focus-at, 2.5 m), K = 12.2 px"


@pytest.mark.parametrize("terminal", [False, True])
def test_train_refiner_draws_its_bars_only_on_a_terminal(tmp_path, monkeypatch, terminal):
    """train-refiner's tqdm bars (the bank's and the steps') wrote carriage-return frames into a log; off a terminal
    they are off now, on one they are drawn (unless --quiet)."""
    pytest.importorskip("torch")
    from bokehray.app import cli

    seen = {}

    class _Train:
        TrainConfig = staticmethod(lambda **kw: kw)

        @staticmethod
        def train(cfg, resume, progress, stop_at):
            seen["progress"] = progress
            return tmp_path / "w.safetensors"

    monkeypatch.setattr(cli, "_refiner_module", lambda name: _Train)
    monkeypatch.setattr(cli, "_check_train_args", lambda args: None)  # the bars, not the checks (a fake trainer)
    if terminal:
        monkeypatch.setattr(sys, "stderr", _Terminal())
    assert main(["train-refiner", "--data", str(tmp_path), "--out", str(tmp_path / "run")]) == 0
    assert seen["progress"] is terminal
