"""`localize` with a Foxglove result MCAP, end to end on the tiny room log (cpu)."""

import numpy as np
import pytest
from support.foxglove_check import cloud_array, cloud_in_frame, read_result

localize_world = pytest.importorskip("support.localize_world")

SCANS = 6


@pytest.fixture(scope="module")
def room(tmp_path_factory, backend):
    from mcl3d.core import runtime

    runtime.init(backend)  # the map is built on it
    d = tmp_path_factory.mktemp("room")
    localize_world.write_log(d / "room.mcap", SCANS)
    localize_world.save_room_map(d / "room.tsdf", 0.1)
    return d


def test_localize_result_mcap_holds_every_channel(room, tmp_path, ti_runtime):
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    cfg = LocalizeConfig()
    cfg.localizer.particles = 3000
    cfg.localizer.init.mode = "gt"
    cfg.result_particles = 1000
    path = tmp_path / "result.mcap"
    result = run(LocalizeRequest(room / "room.mcap", room / "room.tsdf", tmp_path / "out", cfg,
                                 result_mcap=path))
    msgs = read_result(path)  # every channel foxglove.*, every message decoded
    assert set(msgs) == {"/map", "/scan", "/tf", "/estimate", "/estimate/covariance",
                         "/particles", "/hypotheses", "/ground_truth", "/stats", "/log"}
    assert len(msgs["/map"]) == 1 and len(cloud_array(msgs["/map"][0])["x"]) > 1000
    for topic in ("/scan", "/tf", "/estimate", "/particles", "/stats", "/ground_truth"):
        assert len(msgs[topic]) == SCANS, topic
    last = result.results[-1]
    est = msgs["/estimate"][-1].pose.position
    np.testing.assert_allclose([est.x, est.y, est.z], last.T_map_lidar[:3, 3], atol=1e-9)
    particles = cloud_array(msgs["/particles"][-1])
    assert len(particles["x"]) == 1000 and particles["weight"].max() == pytest.approx(1.0)
    stats = {j.name: j.position for j in msgs["/stats"][-1].joints}
    assert stats["ess"] == pytest.approx(last.ess) and stats["error_m"] < 0.1
    scan = cloud_in_frame(msgs["/scan"][-1])  # the scan in the map frame: inside the room
    assert len(scan) > 1000
    assert (scan[:, 0] > -0.5).all() and (scan[:, 0] < 8.5).all()
    assert (scan[:, 1] > -0.5).all() and (scan[:, 1] < 6.5).all()
    assert "converged" in msgs["/log"][0].message


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def watch_live(port: int, seen: dict, connected) -> None:
    """A Foxglove WebSocket client: connects as soon as the server is up, records the
    advertised channels until the server closes."""
    import json
    import time

    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                         open_timeout=5) as ws:
                while True:
                    msg = json.loads(ws.recv(timeout=60))
                    if msg["op"] == "advertise":
                        seen.update({c["topic"]: c["schemaName"] for c in msg["channels"]})
                        connected.set()
        except ConnectionClosed:
            return
        except OSError:
            time.sleep(0.02)


def test_localize_live_serves_the_channels_while_it_runs(room, tmp_path, monkeypatch):
    import threading

    from typer.testing import CliRunner

    from mcl3d.cli import app
    from mcl3d.localization import result_view

    port, seen, connected = free_port(), {}, threading.Event()
    update = result_view.LocalizeView.update

    def update_once_watched(self, *args):  # the first scan waits for the client
        assert connected.wait(60), "no WebSocket client connected"
        update(self, *args)

    monkeypatch.setattr(result_view.LocalizeView, "update", update_once_watched)
    client = threading.Thread(target=watch_live, args=(port, seen, connected), daemon=True)
    client.start()
    r = CliRunner().invoke(app, ["localize", str(room / "room.mcap"), "--map",
                                 str(room / "room.tsdf"), "-o", str(tmp_path / "out"),
                                 "--init", "gt", "--particles", "2000", "--max-scans", "3",
                                 "--backend", "cpu", "--live", "--live-port", str(port)])
    client.join(30)
    assert r.exit_code == 0, r.output
    assert f"ws://127.0.0.1:{port}" in r.output
    assert {"/map", "/scan", "/tf", "/estimate", "/particles", "/stats"} <= set(seen)
    assert all(name.startswith("foxglove.") for name in seen.values())
    assert not list(tmp_path.glob("*.mcap"))  # live only: no file
