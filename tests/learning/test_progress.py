"""Progress output: plain lines in a log (no carriage returns), tqdm on a terminal."""

from __future__ import annotations

import io
import os

import numpy as np

from hilstack.learning.progress import LineProgress, progress


def test_a_log_gets_one_line_per_tenth_and_no_carriage_returns():
    log = io.StringIO()  # not a TTY, like `hil demo > demo.log`
    seen = list(progress(range(400), desc="random rollouts", file=log))
    assert seen == list(range(400))
    text = log.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert len(lines) == 10
    assert lines[0].startswith("random rollouts: 40/400 (10%)")
    assert lines[-1].startswith("random rollouts: 400/400 (100%)")


def test_manual_updates_with_postfix_and_a_last_line_on_close():
    log = io.StringIO()
    bar = progress(total=7, desc="fit", file=log)
    assert isinstance(bar, LineProgress)
    for i in range(5):  # stopped early (e.g. an exception): close() still reports where it got
        bar.set_postfix({"train_loss": f"{0.5 / (i + 1):.4g}"})
        bar.update(1)
    bar.close()
    bar.close()
    lines = log.getvalue().splitlines()
    assert [ln.split(" ")[1] for ln in lines] == ["1/7", "2/7", "3/7", "4/7", "5/7"]
    assert lines[-1].endswith("train_loss=0.1")


def test_a_terminal_gets_a_tqdm_bar():
    from tqdm import tqdm

    master, slave = os.openpty()
    try:
        with os.fdopen(slave, "w", closefd=False) as tty_file:
            bar = progress(total=3, desc="fit", file=tty_file)
            assert isinstance(bar, tqdm)
            bar.close()
    finally:
        os.close(slave)
        os.close(master)


def test_fitting_a_model_into_a_log_writes_plain_lines(capsys):
    from hilstack.learning.datasets import Episode
    from hilstack.learning.dynamics import EnsembleDynamics

    rng = np.random.default_rng(0)
    s = rng.normal(size=(21, 2)).astype(np.float32)
    a = rng.normal(size=(20, 1)).astype(np.float32)
    ep = Episode(states=s, actions=a)
    m = EnsembleDynamics(2, 1, ensemble=1, hidden=(8,))
    m.fit([ep], epochs=20, progress=True)
    err = capsys.readouterr().err  # pytest's captured stderr is not a TTY
    assert "\r" not in err and err.count("\n") == 10 and "fit: 20/20 (100%)" in err and "train_loss=" in err
