"""``usdeform replay`` on the command line: its rate counts the frames' sending only, its log lines name it."""

from __future__ import annotations

import logging
import re

import pytest

pytest.importorskip("pyigtl")

from live_helpers import serve
from usdeform.cli import main
from usdeform.io import write_sequence
from usdeform.live.synthetic import synthetic_scan


def test_replay_prints_the_rate_it_sent_at_and_names_itself(tmp_path, capsys) -> None:
    model, sampled, sweep = synthetic_scan(30)
    write_sequence(tmp_path / "sweep.seq.nrrd", sweep)
    server, thread, out = serve({"model": model, "sampled": sampled}, idle_stop_s=3.0)
    logging.getLogger("usdeform.live").propagate = False  # the command's own handler prints to stderr
    try:
        status = main(["replay", str(tmp_path / "sweep.seq.nrrd"), "--to", f"127.0.0.1:{server.port}", "--rate", "60"])
    finally:
        logging.getLogger("usdeform.live").propagate = True
    thread.join(timeout=60.0)
    captured = capsys.readouterr()
    assert status == 0 and out["result"].frames_corrected == 30
    rate = float(re.search(r"sent 30 frames in [\d.]+ s \(([\d.]+) frames/s\)", captured.out).group(1))  # type: ignore[union-attr]
    assert 50 <= rate <= 61  # the wait for the service to close is not counted (it was 15 frames/s)
    assert "usdeform live:" not in captured.err
