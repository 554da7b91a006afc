"""iwsim play: the protocol, the engine (sessions, batching, recording) and the real server
over real WebSockets, on a tiny world model."""

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from iwsim.cli import main
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.envs import make_env
from iwsim.play import protocol as proto
from iwsim.play.access import TOKEN_ENV, Access, PlayError, bind, resolve_token
from iwsim.play.engine import EPISODE_KEYS, Engine, PlayConfig
from iwsim.play.server import WS_MAX_BYTES, check_bind, running, serve
from iwsim.world_model import WorldModel
from tests.test_dynamics import tiny_world_model

SRC = Path(__file__).resolve().parents[1] / "src"

# -- helpers -------------------------------------------------------------------------------


def receive(ws, kind: str, timeout: float = 10.0, where=lambda m: True):
    """The next message of ``kind`` (a frame header + views for "frame") that satisfies ``where``."""
    deadline = time.monotonic() + timeout
    while True:
        data = ws.recv(timeout=max(0.01, deadline - time.monotonic()))
        if isinstance(data, bytes):
            header, views = proto.unpack_frame(data)
            if kind == "frame" and where(header):
                return header, views
        else:
            msg = json.loads(data)
            if msg["type"] == kind and where(msg):
                return msg


def close_code(ws, timeout: float = 10.0) -> int:
    """Read until the server closes the connection; its close code."""
    deadline = time.monotonic() + timeout
    with pytest.raises(ConnectionClosed) as closed:
        while time.monotonic() < deadline:
            ws.recv(timeout=max(0.01, deadline - time.monotonic()))
    return closed.value.rcvd.code


def engine(**cfg) -> Engine:
    return Engine(tiny_world_model(), PlayConfig(**cfg))


def action(seq: int, a) -> proto.Action:
    return proto.Action(seq, tuple(float(v) for v in a))


# -- protocol ------------------------------------------------------------------------------

BAD = {
    "oversized": ('{"type": "action", "pad": "' + "x" * proto.MAX_MESSAGE_BYTES + '"}', "over the limit"),
    "binary": (b'{"type": "record"}', "binary"),
    "not json": ("{type: record", "not valid JSON"),
    "not an object": ("[1, 2]", "JSON object"),
    "no type": ('{"seq": 1}', "JSON object"),
    "unknown type": ('{"type": "teleport"}', "unknown message type 'teleport'"),
    "short action": ('{"type": "action", "seq": 1, "action": [0, 0, 0]}', "list of 4 numbers"),
    "text action": ('{"type": "action", "seq": 1, "action": [0, 0, "0", 0]}', "list of 4 numbers"),
    "bool action": ('{"type": "action", "seq": 1, "action": [0, 0, true, 0]}', "list of 4 numbers"),
    "nan action": ('{"type": "action", "seq": 1, "action": [0, NaN, 0, 0]}', "finite"),
    "huge action": ('{"type": "action", "seq": 1, "action": [0, 1e999, 0, 0]}', "finite"),
    "huge integer action": ('{"type": "action", "seq": 1, "action": [0, 1' + "0" * 400 + ', 0, 0]}', "finite"),
    "no seq": ('{"type": "action", "action": [0, 0, 0, 0]}', "integer 'seq'"),
    "negative seq": ('{"type": "action", "seq": -1, "action": [0, 0, 0, 0]}', "'seq' must be an integer"),
    "float seq": ('{"type": "action", "seq": 1.5, "action": [0, 0, 0, 0]}', "'seq' must be an integer"),
    "bad source": ('{"type": "reset", "source": "dream"}', "'source' must be one of"),
    "bad seed": ('{"type": "reset", "seed": -3}', "'seed' must be an integer"),
    "bad side": ('{"type": "side_by_side", "on": "yes"}', "'on' must be true or false"),
    "deep json": ("[" * 2000 + "]" * 2000, "not valid JSON|JSON object"),
}


@pytest.mark.parametrize("name", BAD)
def test_bad_messages_are_protocol_errors(name):
    data, match = BAD[name]
    with pytest.raises(proto.ProtocolError, match=match):
        proto.parse(data, 4)


def test_good_messages_parse():
    assert proto.parse('{"type": "action", "seq": 3, "action": [0.1, 0, -0.1, 0.2]}', 4) == \
        proto.Action(3, (0.1, 0.0, -0.1, 0.2))
    assert proto.parse('{"type": "reset", "source": "store", "seed": 7}', 4) == proto.Reset("store", 7)
    assert proto.parse('{"type": "reset"}', 4) == proto.Reset("mujoco", None)
    assert proto.parse('{"type": "side_by_side", "on": true}', 4) == proto.SideBySide(True)
    for name in ("record", "save", "discard"):
        assert proto.parse(json.dumps({"type": name}), 4) == proto.Command(name)


def test_frame_messages_round_trip():
    views = [np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8) for _ in range(2)]
    header, back = proto.unpack_frame(proto.pack_frame({"size": 8, "views": ["a", "b"], "step": 3}, views))
    assert header["step"] == 3 and all(np.array_equal(a, b) for a, b in zip(views, back))


# -- engine --------------------------------------------------------------------------------


def test_sessions_are_bounded_and_targets_clipped():
    eng = engine(max_sessions=2)
    a, b = eng.open(), eng.open()
    assert a is not None and b is not None and eng.open() is None
    assert eng.handle(a, action(5, [1.0, -1.0, 0.1, 0.0])) == []
    np.testing.assert_allclose(a.target, [0.22, -0.22, 0.1, 0.0], atol=1e-6)
    assert a.ack == 5
    eng.close(b)
    assert eng.open() is not None


def test_sessions_step_together_as_they_would_alone():
    """Sessions opened at different times share forward passes (grouped by context
    length) and get the frames they would get alone."""
    targets = np.random.default_rng(0).uniform(-0.2, 0.2, (20, 4)).astype(np.float32)
    alone = engine()
    s = alone.open()
    alone.handle(s, proto.Reset("mujoco", 2))
    solo = []
    for t in range(12):
        alone.handle(s, action(t, targets[t]))
        alone.tick()
        solo.append(s.frame)
    shared = engine()
    first = shared.open()
    shared.handle(first, proto.Reset("mujoco", 1))
    for _ in range(3):  # the first session runs ahead, so the two differ in context length
        shared.tick()
    s = shared.open()
    shared.handle(s, proto.Reset("mujoco", 2))
    for t in range(12):
        shared.handle(s, action(t, targets[t]))
        stepped = shared.tick()
        assert stepped == [first, s]
        assert np.abs(s.frame.astype(int) - solo[t]).max() <= 1, t
    assert s.step == 12 and first.step == 15


def test_record_save_and_discard(tmp_path):
    store = tmp_path / "demos.zarr"
    eng = engine(record_to=store)
    s = eng.open()
    start = s.frame.copy()
    assert "recording is off" not in eng.handle(s, proto.Command("record"))[0]
    targets = np.linspace(-0.1, 0.1, 5 * 4, dtype=np.float32).reshape(5, 4)
    shown = []
    for t in range(5):
        eng.handle(s, action(t, targets[t]))
        shown.append(s.frame.copy())
        eng.tick()
    assert json.loads(eng.handle(s, proto.Command("save"))[0])["message"] == "saving 5 steps"
    eng.recorder.close()  # waits for the write
    (who, text), = eng.finished_saves()
    # the store's name only: no filesystem path goes to clients
    assert who is s and json.loads(text) == {"type": "saved", "episode": 0, "steps": 5, "store": "demos.zarr"}
    assert json.loads(eng.hello(s))["recording_to"] == "demos.zarr"
    back = EpisodeStore.open(store)
    ep = back.episode(0)
    assert sorted(ep) == sorted(EPISODE_KEYS) and back.seeds == [s.seed]
    np.testing.assert_array_equal(ep["img"][0], start)
    np.testing.assert_array_equal(ep["img"], np.stack(shown))  # the frame shown before each action
    np.testing.assert_allclose(ep["action"], targets)
    assert ep["state"].shape == (5, 4) and ep["iou"].shape == (5,)
    assert back.attrs["policy"] == "teleop" and back.attrs["image_size"] == 64 and back.attrs["fps"] == 10

    # discard, and errors for commands out of place, leave the store as it was
    eng = engine(record_to=store)
    s = eng.open()
    assert "nothing to save" in eng.handle(s, proto.Command("save"))[0]
    eng.handle(s, proto.Command("record"))
    assert "already recording" in eng.handle(s, proto.Command("record"))[0]
    eng.tick()
    assert "discarded 1 steps" in eng.handle(s, proto.Command("discard"))[0]
    eng.handle(s, proto.Command("record"))
    eng.tick()
    assert "discarded by the restart" in eng.handle(s, proto.Reset("mujoco", 3))[0]
    eng.handle(s, proto.Command("record"))
    eng.tick()
    eng.close(s)  # the client vanished mid-recording
    eng.shutdown()
    assert EpisodeStore.open(store).n_episodes == 1


def test_recording_needs_a_store_and_a_compatible_one(play_store, tmp_path):
    eng = engine()
    s = eng.open()
    assert "--record-to" in eng.handle(s, proto.Command("record"))[0]
    with pytest.raises(StoreError, match="record into another store"):
        engine(record_to=play_store)  # a collect store: other arrays


def test_side_by_side_and_store_starts(play_store):
    eng = engine()
    s = eng.open()
    assert "--store" in eng.handle(s, proto.Reset("store", 1))[0]
    events = eng.handle(s, proto.SideBySide(True))
    assert "side by side on" in events[0]
    header, views = proto.unpack_frame(eng.frame_message(s))
    assert header["views"] == ["world_model", "mujoco"] and header["step"] == 0
    mujoco = make_env("pusht", 64)
    obs, _ = mujoco.reset(seed=s.seed)
    np.testing.assert_array_equal(views[0], obs["pixels"])  # both start from the seed's frame
    np.testing.assert_array_equal(views[1], obs["pixels"])
    eng.handle(s, action(0, [0.1, 0.1, -0.1, -0.1]))
    eng.tick()
    obs, *_ = mujoco.step(np.array([0.1, 0.1, -0.1, -0.1], np.float32))
    np.testing.assert_array_equal(s.twin_frame, obs["pixels"])  # the twin follows the same actions
    eng.handle(s, proto.SideBySide(False))
    assert proto.unpack_frame(eng.frame_message(s))[0]["views"] == ["world_model"]

    eng = engine(store=play_store)
    s = eng.open()
    eng.handle(s, proto.SideBySide(True))
    eng.handle(s, proto.Reset("store", 4))
    header, views = proto.unpack_frame(eng.frame_message(s))
    assert header["source"] == "store" and header["views"] == ["world_model", "mujoco"]
    stored = EpisodeStore.open(play_store).array("img")[:]
    assert any(np.array_equal(views[0], f) for f in stored)
    assert np.mean(views[0] != views[1]) < 0.02  # MuJoCo restarted from the stored state


def test_side_by_side_on_pile_sweeping(pile_model):
    """A world model of another MuJoCo task plays beside its own simulator, with its score."""
    eng = Engine(WorldModel.load(pile_model["checkpoint"]), PlayConfig())
    s = eng.open()
    assert "side by side on" in eng.handle(s, proto.SideBySide(True))[0]
    sim = make_env("pilesweep", 64)
    obs, info = sim.reset(seed=s.seed)
    header, views = proto.unpack_frame(eng.frame_message(s))
    assert header["views"] == ["world_model", "mujoco"] and header["mujoco_iou"] == info["score"]
    np.testing.assert_array_equal(views[1], obs["pixels"])
    eng.handle(s, action(0, [0.1, 0.1, -0.1, -0.1]))
    eng.tick()
    obs, _, _, _, info = sim.step(np.array([0.1, 0.1, -0.1, -0.1], np.float32))
    np.testing.assert_array_equal(s.twin_frame, obs["pixels"])
    assert s.twin_iou == info["score"] and 0 <= s.iou <= 1


# -- the server over real sockets ------------------------------------------------------------


def test_server_streams_frames_and_survives_bad_messages():
    eng = engine(hz=20)
    with running(eng) as srv, connect(srv.ws) as ws:
        hello = receive(ws, "hello")
        assert hello["image_size"] == 64 and hello["hz"] == 20 and hello["reset_sources"] == ["mujoco"]
        first, _ = receive(ws, "frame")
        for data in [BAD[k][0] for k in BAD if k != "deep json"] + [b"\x00" * 100]:
            ws.send(data)
            assert receive(ws, "error")["message"]
        ws.send(json.dumps({"type": "action", "seq": 41, "action": [0.05, 0.05, -0.05, -0.05]}))
        header, views = receive(ws, "frame", where=lambda h: h["ack"] == 41)
        assert header["step"] > first["step"] and header["action"] == pytest.approx([0.05, 0.05, -0.05, -0.05])
        assert views[0].shape == (64, 64, 3)
        ws.send(json.dumps({"type": "reset", "seed": 5}))
        assert receive(ws, "frame", where=lambda h: h["seed"] == 5 and h["step"] == 0)
        # a message over the transport limit closes only this connection
        ws.send("x" * (WS_MAX_BYTES + 1))
        assert close_code(ws) == 1009
        with connect(srv.ws) as again:
            assert receive(again, "hello")


def test_server_token_origin_and_session_limit():
    eng = engine(max_sessions=1)
    with running(eng, token="s3cret-token", origins=["http://tool.example:9000"]) as srv:
        base = f"ws://{srv.address}/ws"
        for query in ("", "?token=wrong", "?token=wrong&token=s3cret-token", "?token=s3cret-token&token=s3cret-token"):
            with connect(base + query) as ws:  # missing, wrong or repeated: refused
                assert "token" in receive(ws, "error")["message"]
                assert close_code(ws) == 1008
        # a foreign page is refused at the handshake, even with the token
        for origin in ("http://evil.example", f"http://evil.example:{srv.address.split(':')[1]}", "null"):
            with pytest.raises(InvalidStatus) as refused:
                connect(srv.ws, origin=origin)
            assert refused.value.response.status_code == 403
        for origin in (f"http://{srv.address}", "http://tool.example:9000"):  # its own page; --allow-origin
            with connect(srv.ws, origin=origin) as ws:
                assert receive(ws, "hello")
        with connect(srv.ws) as ws:
            assert receive(ws, "hello")
            with connect(srv.ws) as extra:
                assert "busy" in receive(extra, "busy")["message"]
                assert close_code(extra) == 1013
            assert receive(ws, "frame")  # the first session goes on


def test_a_client_vanishing_mid_recording_leaves_no_episode(tmp_path):
    store = tmp_path / "demos.zarr"
    eng = engine(record_to=store, hz=20)
    with running(eng) as srv:
        ws = connect(srv.ws)
        receive(ws, "hello")
        ws.send(json.dumps({"type": "record"}))
        receive(ws, "frame", where=lambda h: (h["recording"] or 0) >= 3)
        ws.close()  # gone, without save or discard
        deadline = time.monotonic() + 10
        while eng.sessions and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not eng.sessions
        with connect(srv.ws) as ws:  # the server serves on; a saved take lands
            receive(ws, "hello")
            ws.send(json.dumps({"type": "record"}))
            receive(ws, "frame", where=lambda h: (h["recording"] or 0) >= 2)
            ws.send(json.dumps({"type": "save"}))
            saved = receive(ws, "saved")
    assert saved["episode"] == 0
    assert EpisodeStore.open(store).n_episodes == 1


def test_binding_beyond_loopback_needs_a_token(capsys, tmp_path):
    check_bind("127.0.0.1", None)
    check_bind("0.0.0.0", "t")
    with pytest.raises(ValueError, match="--token"):
        check_bind("0.0.0.0", None)
    assert main(["play", "--host", "0.0.0.0", "--checkpoint", str(tmp_path)]) == 1
    assert "refusing to bind 0.0.0.0 without --token" in capsys.readouterr().err
    assert main(["play", "--checkpoint", str(tmp_path / "none")]) == 1
    assert "not a checkpoint directory" in capsys.readouterr().err


def test_page_is_served_with_the_token_only_to_this_machine():
    import urllib.error
    import urllib.request

    def get(url: str, host: str | None = None) -> str:
        request = urllib.request.Request(url, headers={"Host": host} if host else {})
        return urllib.request.urlopen(request).read().decode()

    with running(engine()) as srv:
        port = srv.address.split(":")[1]
        page = get(srv.page)
        script = get(srv.page + "play.js")
        assert f'<meta name="iwsim-token" content="{srv.token}">' in page
        assert srv.token in get(srv.page, f"localhost:{port}")
        # a foreign name resolving here (DNS rebinding) gets nothing, not even the page
        for host in (f"evil.example:{port}", "127.0.0.1:1"):
            with pytest.raises(urllib.error.HTTPError) as refused:
                get(srv.page, host)
            assert refused.value.code == 421
    assert '<script src="/play.js">' in page and "new WebSocket" in script


def test_page_on_all_interfaces_carries_no_token_for_other_names():
    import urllib.request

    with running(engine(), host="0.0.0.0", token="chosen-token") as srv:
        port = srv.address.split(":")[1]
        mine = urllib.request.urlopen(f"http://127.0.0.1:{port}/").read().decode()
        other = urllib.request.urlopen(urllib.request.Request(f"http://127.0.0.1:{port}/",
                                                              headers={"Host": f"myhost.lan:{port}"})).read().decode()
    assert "chosen-token" in mine and "chosen-token" not in other


def test_token_comes_from_a_file_or_the_environment(tmp_path):
    file = tmp_path / "token"
    file.write_text("from-the-file\n")
    env = {TOKEN_ENV: "from-the-env"}
    assert resolve_token("from-the-flag", file, env) == ("from-the-file", f"--token-file {file}")
    assert resolve_token("from-the-flag", None, {TOKEN_ENV: "from-the-env"}) == ("from-the-env", f"${TOKEN_ENV}")
    assert resolve_token("from-the-flag", None, {}) == ("from-the-flag", "--token")
    assert resolve_token(None, None, {}) == (None, "random")
    for bad in ("short", "has space in it", ""):
        file.write_text(bad)
        with pytest.raises(ValueError, match="at least 8 printable characters"):
            resolve_token(None, file, {})
    with pytest.raises(ValueError, match="cannot read the token file"):
        resolve_token(None, tmp_path / "missing", {})
    with pytest.raises(ValueError, match=r"\$IWSIM_PLAY_TOKEN must be at least 8"):  # set but empty
        resolve_token("from-the-flag", None, {TOKEN_ENV: ""})


def test_play_never_logs_the_token(tmp_path, monkeypatch, caplog):
    import iwsim.play.server
    import iwsim.world_model

    served = {}
    monkeypatch.setattr(iwsim.world_model.WorldModel, "load", staticmethod(lambda *a, **k: tiny_world_model()))
    monkeypatch.setattr(iwsim.play.server, "serve", lambda engine, sock, access: served.update(access=access))
    (tmp_path / "token").write_text("file-secret-123")
    monkeypatch.setenv(TOKEN_ENV, "env-secret-1234")
    with caplog.at_level("INFO"):
        assert main(["play", "--host", "0.0.0.0", "--port", "0", "--token-file", str(tmp_path / "token")]) == 0
    assert served["access"].token == "file-secret-123"
    assert "serving" in caplog.text and "file-secret-123" not in caplog.text and "--token-file" in caplog.text


def test_play_on_a_taken_port_exits_at_once(tmp_path):
    """A real `iwsim play` process: one line, exit code 1 (it used to hang: the timeout fails
    the test). The checkpoint does not exist, so the port's error proves the port is checked
    before anything slow is loaded; no wall-clock bound, which a loaded machine breaks."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = subprocess.run([sys.executable, "-m", "iwsim.cli", "play", "--port", str(port),
                               "--checkpoint", str(tmp_path / "unused")], capture_output=True, text=True, timeout=60,
                              env={**os.environ, "PYTHONPATH": str(SRC)})
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip() == (f"iwsim: error: cannot serve on 127.0.0.1:{port}: the address is already in use "
                                   "(another iwsim play?); choose another --port.")


def test_a_failing_web_server_stops_the_engine_and_the_process(monkeypatch):
    import uvicorn

    def crash(self, sockets=None):
        raise RuntimeError("the event loop broke")

    monkeypatch.setattr(uvicorn.Server, "run", crash)
    eng = engine()
    shut = []
    monkeypatch.setattr(eng, "shutdown", lambda: shut.append(True))
    sock = bind("127.0.0.1", 0)
    t0 = time.monotonic()
    with pytest.raises(PlayError, match="the web server did not start: RuntimeError: the event loop broke"):
        serve(eng, sock, Access.create(None, "127.0.0.1", sock.getsockname()[1]))
    assert time.monotonic() - t0 < 5 and shut == [True] and sock.fileno() == -1


def test_play_config_rejects_bad_values():
    for bad in ({"hz": 0}, {"hz": 100}, {"max_sessions": 0}, {"max_record_steps": 0}):
        with pytest.raises(ValueError):
            PlayConfig(**bad)


def test_outbox_is_bounded_for_a_client_that_never_reads():
    """Issue 26: the per-connection event queue grew without bound (~10 MiB/s)."""
    import asyncio

    from iwsim.play.server import MAX_UNSENT_EVENTS, Outbox

    class Stuck:  # a socket whose sends never complete
        async def send_text(self, text):
            await asyncio.Event().wait()

    async def flood() -> Outbox:
        out = Outbox(Stuck())
        task = asyncio.create_task(out.run())
        for i in range(10 * MAX_UNSENT_EVENTS):
            out.event(f"error {i}")
            out.put_frame(b"x" * 100)
            await asyncio.sleep(0)
        task.cancel()
        return out

    out = asyncio.run(flood())
    assert out.overflow and len(out.events) <= MAX_UNSENT_EVENTS


def test_server_drops_a_flooding_client_that_never_reads_and_serves_the_others():
    import socket
    from urllib.parse import urlparse

    eng = engine(max_sessions=2)
    with running(eng) as srv:
        url = urlparse(srv.ws)
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # fills at once when nobody reads
        sock.connect((url.hostname, url.port))
        with connect(srv.ws, sock=sock, max_queue=1) as flooder:
            bad = json.dumps({"type": "action", "seq": 1, "action": [0, 0, 0]})
            t0 = time.monotonic()
            with pytest.raises(ConnectionClosed):  # it never reads: the server gives up on it, well
                while time.monotonic() < t0 + 60:  # before its keepalive would (20 s pings here)
                    flooder.send(bad)
            assert time.monotonic() - t0 < 30  # under 1 s here; the old code took ~50 s (keepalive)
        with connect(srv.ws) as ws:  # a well-behaved client still gets its frames
            receive(ws, "frame")


def test_message_budget_allows_the_page_rate_and_cuts_a_flood():
    from iwsim.play.server import MAX_MESSAGES_PER_STEP, MessageBudget

    for hz in (10, 60):  # the page's slowest and fastest step rates
        now = [0.0]
        rate = MAX_MESSAGES_PER_STEP * hz
        budget = MessageBudget(rate, clock=lambda now=now: now[0])
        for _ in range(60 * hz):  # 60 s of the page's most: two actions per step, and a command
            now[0] += 1 / hz
            assert all(budget.take() for _ in range(3))
        flood = [budget.take() for _ in range(5 * rate)]  # all in one instant
        assert flood.index(False) == 2 * rate - 3  # the burst (less this step's 3), no more


def test_server_drops_a_client_that_sends_too_fast_and_serves_the_others():
    """Issue 26 soak: a flood of messages took the server's time (the others' frames/s 9.9 -> 5.7)."""
    from iwsim.play.server import MAX_MESSAGES_PER_STEP, RATE_REASON

    eng = engine(max_sessions=2)
    with running(eng) as srv:
        with connect(srv.ws) as flooder:
            receive(flooder, "hello")
            msg = json.dumps({"type": "action", "seq": 1, "action": [0.0, 0.0, 0.0, 0.0]})
            with pytest.raises(ConnectionClosed) as closed:
                for _ in range(100_000):
                    flooder.send(msg)
                while True:
                    flooder.recv(timeout=10)
        assert closed.value.rcvd.code == 1008 and closed.value.rcvd.reason == RATE_REASON.format(
            f"{MAX_MESSAGES_PER_STEP * eng.cfg.hz:g}")
        with connect(srv.ws) as ws:
            receive(ws, "frame")
