"""The benchmarks' page-like client of ``iwsim play`` (``iwsim.play.client``, driven by
``bench/bench_play.py`` and ``bench/bench_play_soak.py``) against a real server in this
process, and the latency summary their records hold."""

import numpy as np
import pytest

from iwsim.play.client import client, free_port, summary
from iwsim.play.server import running
from tests.test_play import engine


def test_the_page_like_client_records_frames_latencies_and_step_times():
    with running(engine(hz=20)) as srv:
        out: dict = {}
        client(srv.ws, hz=20, warmup=0.2, seconds=1.5, seed=0, out=out)
    assert len(out["frame_times"]) == len(out["step_ms"]) > 5  # 20 Hz for 1.5 s, beside other work
    assert np.all(np.diff(out["frame_times"]) >= 0) and all(ms >= 0 for ms in out["step_ms"])
    assert out["latencies"] and all(0 < ms < 1500 for ms in out["latencies"])  # a press every 0.4-0.6 s, acked


def test_latency_summary_and_a_free_port():
    assert summary(np.array([])) == {"n": 0}
    s = summary(np.array([10.0, 20.0, 30.0, 40.0]))
    assert s["n"] == 4 and s["p50"] == 25.0 and s["mean"] == 25.0 and s["max"] == 40.0
    assert s["p95"] == pytest.approx(38.5)
    assert 0 < free_port() < 65536
