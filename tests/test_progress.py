"""splattwin.progress: plain lines in a log (start, at most one per interval, end), a rich bar on a terminal."""

import io

import numpy as np
import pytest

from splattwin.progress import DEFAULT_INTERVAL, Progress, format_duration, plain_interval, track


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def lines(stream: io.StringIO) -> list[str]:
    return stream.getvalue().splitlines()


def test_plain_lines_start_interval_and_end():
    s, clock = io.StringIO(), Clock()
    with Progress(100, "train", unit="it", stream=s, interval=10.0, clock=clock) as bar:
        assert lines(s) == ["train: 0/100 it (0 %), 0 s"]
        for _ in range(30):          # 30 updates within 3.75 s: no new line
            clock.t += 0.125
            bar.update(1)
        assert len(lines(s)) == 1
        clock.t += 6.25              # 10 s since the first line
        bar.set_postfix(loss="0.0871", gaussians=15528)
        bar.update(10)
        assert lines(s)[-1] == "train: 40/100 it (40 %), 10 s, ETA 15 s, loss 0.0871, gaussians 15528"
        clock.t += 5.0
        bar.update(60)               # only 5 s later: no line until the end
        assert len(lines(s)) == 2
    assert lines(s)[-1] == "train: 100/100 it done in 15 s, loss 0.0871, gaussians 15528"
    assert "\r" not in s.getvalue()


def test_eta_counts_from_a_resumed_start():
    s, clock = io.StringIO(), Clock()
    bar = Progress(3000, "train", stream=s, interval=1.0, clock=clock, initial=2000)
    clock.t += 10.0
    bar.update(100)                  # 100 steps in 10 s, 900 left: 90 s, not 15 s
    assert lines(s)[-1] == "train: 2100/3000 it (70 %), 10 s, ETA 1 min 30 s"
    bar.close(failed=True)
    bar.close()                      # idempotent
    assert lines(s)[-1].startswith("train: 2100/3000 it stopped after 10 s")
    assert len(lines(s)) == 3
    # an exception leaving the block: "stopped after"; a loop ending early on its own (convergence): "done in"
    s = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        with Progress(10, "train", stream=s, interval=1e9) as bar:
            bar.update(4)
            raise KeyboardInterrupt
    assert lines(s)[-1].startswith("train: 4/10 it stopped after")
    s = io.StringIO()
    with Progress(3, "fusion rounds", unit="round", stream=s, interval=1e9) as bar:
        bar.update(2)
    assert lines(s)[-1].startswith("fusion rounds: 2/3 round done in")


def test_disabled_writes_nothing_and_unknown_total():
    s = io.StringIO()
    with Progress(10, "x", enabled=False, stream=s) as bar:
        bar.update(5)
    assert s.getvalue() == ""
    s, clock = io.StringIO(), Clock()
    with Progress(None, "scoring clip.mp4", unit="frame", stream=s, interval=1.0, clock=clock) as bar:
        clock.t += 2
        bar.update(7)
    assert lines(s) == ["scoring clip.mp4: 0 frame, 0 s", "scoring clip.mp4: 7 frame, 2 s",
                        "scoring clip.mp4: 7 frame done in 2 s"]


def test_track_yields_everything_and_reports_the_count():
    s = io.StringIO()
    out = list(track(np.arange(5), "eval", unit="view", stream=s, interval=1e9))
    assert [int(v) for v in out] == [0, 1, 2, 3, 4]
    assert lines(s)[0] == "eval: 0/5 view (0 %), 0 s"
    assert lines(s)[-1].startswith("eval: 5/5 view done in")


def test_terminal_gets_a_rich_bar():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    s = Tty()
    with Progress(4, "fusion rounds", unit="round", stream=s) as bar:
        bar.set_postfix(changed=12)
        for _ in range(4):
            bar.update(1)
    out = s.getvalue()
    assert "fusion rounds" in out and "4/4" in out and "changed 12" in out
    assert "\x1b[" in out            # a live terminal bar (ANSI control), not plain lines
    assert "done in" not in out


@pytest.mark.parametrize("raw,want", [("3", 3.0), ("0.5", 0.5), ("", DEFAULT_INTERVAL), ("-1", DEFAULT_INTERVAL),
                                      ("nan", DEFAULT_INTERVAL), ("soon", DEFAULT_INTERVAL)])
def test_interval_from_the_environment(monkeypatch, raw, want):
    monkeypatch.setenv("SPLATTWIN_PROGRESS_INTERVAL", raw)
    assert plain_interval() == want


def test_format_duration():
    assert [format_duration(x) for x in (0, 42.4, 185, 3720)] == ["0 s", "42 s", "3 min 5 s", "1 h 2 min"]


def test_a_broken_log_does_not_stop_the_work():
    s = io.StringIO()
    bar = Progress(3, "x", stream=s)
    s.close()
    bar.update(3)
    bar.close()


def test_track_says_stopped_when_its_loop_body_raised():
    """A Ctrl-C in the loop body reaches `track` only as GeneratorExit: it printed "label maps: 0/10 view
    done in 0 s" for an interrupted loop. Done only when every item was."""
    s = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        for _ in track(range(10), "label maps", unit="view", stream=s, interval=1e9):
            raise KeyboardInterrupt
    import gc

    gc.collect()
    assert lines(s)[-1].startswith("label maps: 0/10 view stopped after")


def test_eta_leaves_out_a_slow_first_unit():
    """The first training step on a fresh numba cache took 59 s; the ETA of the 300-step run then read
    4 h 52 min. The rate counts from the first unit on, and the line of the first unit alone has no ETA:
    a default build of the real statue logged "train: 1/3000 it (0 %), 29 s, ETA 24 h 0 min" (numba
    compiling), then "ETA 2 min 2 s" 10 s later."""
    s, clock = io.StringIO(), Clock()
    bar = Progress(300, "train", stream=s, interval=0.0, clock=clock)
    clock.t += 59.0
    bar.update(1)
    assert lines(s)[-1] == "train: 1/300 it (0 %), 59 s"      # one unit is all start-up: no rate yet
    clock.t += 1.0
    bar.update(1)
    assert lines(s)[-1] == "train: 2/300 it (1 %), 1 min 0 s, ETA 4 min 58 s"
    bar.close()
