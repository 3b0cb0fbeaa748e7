"""`SharedMemoryClient` against a live server with the system shared-memory extension on: the
pixels and points of examples/frame.json through the client's region give the keypoints of
`Client.predict` for the same frame; what it refuses; and that it leaves nothing behind."""

import os
from pathlib import Path

import live_server
import numpy as np
import pytest

from posefuse_client import Client, Frame, PosefuseError, SharedMemoryClient
from posefuse_client.shared_memory import K


@pytest.fixture(scope="module")
def shm_server(tmp_path_factory):
    """`posefuse serve --system-shared-memory` on a free loopback port."""
    if reason := live_server.missing_reason():
        pytest.skip(f"no live server: {reason}")
    s = live_server.start(tmp_path_factory.mktemp("shm-server"), flags=("--system-shared-memory",))
    yield s
    live_server.stop(s)


def test_shared_memory_answers_as_the_json_api(shm_server, raw_frame_json):
    frame = Frame.from_json(raw_frame_json)
    with Client(shm_server.http_url) as c:
        want = c.predict(frame)
    with SharedMemoryClient(shm_server.http_url) as s:
        region = Path("/dev/shm") / s.region
        assert region.exists()
        got = s.predict(frame)
        # the same frame again, its pixels given as an array: the same answer
        again = s.predict(Frame(frame.calibration, frame.points, frame.persons, image=frame.image_rgb.to_array()))
    assert not region.exists(), "closing removes the region"
    m = len(frame.persons)
    assert got.ids == [p.id for p in frame.persons]
    assert got.keypoints_3d.shape == (m, K, 3) and got.scores.shape == (m, K)
    assert got.status == ["ok"] * m
    for i, pose in enumerate(want.persons):
        assert got.mode[i] == pose.mode
        assert got.num_points[i] == pose.num_points
        np.testing.assert_allclose(got.keypoints_3d[i], pose.keypoints_3d, atol=1e-5)
        np.testing.assert_allclose(got.keypoints_2d[i], pose.keypoints_2d, atol=1e-3)
    np.testing.assert_array_equal(again.keypoints_3d, got.keypoints_3d)
    status = Client(shm_server.http_url)._http.get("/v2/systemsharedmemory/status").json()
    assert status == [], "closing unregisters the region"


def test_what_shared_memory_cannot_carry_is_refused(shm_server, frame_json, raw_frame_json):
    with SharedMemoryClient(shm_server.http_url, capacity=1 << 20) as s:
        with pytest.raises(ValueError, match="pixels"):
            s.predict(frame_json)  # a JPEG: the server would have to decode it
        with pytest.raises(ValueError, match="capacity"):
            s.predict(raw_frame_json)  # 1.5 MB of pixels in a 1 MB region
        wrong = dict(raw_frame_json, persons=[dict(raw_frame_json["persons"][0], id="a"),
                                              dict(raw_frame_json["persons"][0], id="a")])
    with SharedMemoryClient(shm_server.http_url) as s:
        with pytest.raises(PosefuseError) as e:
            s.predict(wrong)
    assert e.value.http_status == 400 and e.value.code == "invalid_field"


def test_a_server_without_the_extension_refuses_the_region(server):
    with pytest.raises(PosefuseError) as e:
        SharedMemoryClient(server.http_url)
    assert (e.value.code, e.value.http_status) == ("forbidden", 403)
    assert "--system-shared-memory" in e.value.message
    left = list(Path("/dev/shm").glob(f"posefuse-client-{os.getpid()}-*"))
    assert not left, "a refused client leaves no region"
