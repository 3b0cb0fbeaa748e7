"""The HTTP clients, sync and async, end to end against a live `posefuse serve`."""

import asyncio
import copy
import json

import httpx
import numpy as np
import pytest

from posefuse_client import AsyncClient, Client, Frame, PosefuseError


def bad_frame(frame_json: dict) -> dict:
    """A frame the server must refuse naming the field: an intrinsic with 3 numbers instead of 9."""
    bad = copy.deepcopy(frame_json)
    bad["calibration"]["intrinsic"] = bad["calibration"]["intrinsic"][:3]
    return bad


def check_pose(response, frame: Frame, manifest: dict) -> None:
    """Every requested person is answered or skipped, in order, with keypoints near its box."""
    assert response.model_name == manifest["name"] and response.model_version == manifest["version"]
    answered = [p.id for p in response.persons] + [s.id for s in response.skipped]
    assert sorted(answered) == sorted(p.id for p in frame.persons)
    assert response.persons, "the example frame has persons with LiDAR points"
    boxes = {p.id: p.box_3d for p in frame.persons}
    for pose in response.persons:
        assert pose.keypoints_3d.shape == (13, 3) and np.isfinite(pose.keypoints_3d).all()
        assert pose.keypoints_2d.shape == (13, 2) and pose.scores.shape == (13,)
        assert pose.names[0] == "nose" and pose.waymo_types[0] == 1
        assert pose.mode in ("fusion", "lidar", "camera") and pose.num_points > 0
        box = boxes[pose.id]
        centre = np.array([box.center_x, box.center_y, box.center_z])
        reach = 0.5 * np.linalg.norm([box.length, box.width, box.height]) + 0.5
        assert (np.linalg.norm(pose.keypoints_3d - centre, axis=1) < reach).all(), pose.id


def test_sync_http_client_calls_every_endpoint(server, frame_json, frames_json):
    frame = Frame.from_json(frame_json)
    with Client(server.http_url) as client:
        assert client.healthy() and client.ready()
        manifest = client.models()
        assert manifest["name"] == "default"
        assert "/v1/poses" in client.openapi()["paths"]

        response = client.predict(frame)
        check_pose(response, frame, manifest)
        assert "posefuse_request_seconds" in client.metrics()
        # The client's arrays are the server's JSON numbers.
        raw = httpx.post(f"{server.http_url}/v1/poses", json=frame_json, timeout=30).json()
        first = raw["persons"][0]
        np.testing.assert_allclose(response.persons[0].keypoints_3d, [k["xyz"] for k in first["keypoints"]])
        assert response.person(first["id"]).mode == first["mode"]

        # A dict body is sent as is; the same frame gets the same poses.
        again = client.predict(frame_json)
        np.testing.assert_allclose(again.persons[0].keypoints_3d, response.persons[0].keypoints_3d, atol=1e-5)

        report = client.evaluate(frames_json)
        assert report["failed_frames"] == 0 and len(report["predictions"]) == len(frames_json)
        assert report["metrics"]["all"]


def test_sync_http_batch_streams_in_order_with_error_items(server, frames_json):
    frames = [Frame.from_json(f) for f in frames_json]
    inputs = [frames[0], bad_frame(frames_json[1]), *frames[1:]]
    with Client(server.http_url) as client:
        # chunk_size 2: several requests, indices continue across them.
        results = list(client.predict_batch(iter(inputs), chunk_size=2))
        single = client.predict(frames[0])
    assert [r.index for r in results] == list(range(len(inputs)))
    assert results[1].error is not None and not results[1].ok
    assert results[1].error.code == "invalid_field" and results[1].error.field == "calibration.intrinsic"
    for r, frame in zip([results[0], *results[2:]], frames, strict=True):
        assert r.ok and r.response.frame_id == frame.frame_id
    np.testing.assert_allclose(results[0].response.persons[0].keypoints_3d, single.persons[0].keypoints_3d, atol=1e-5)


def test_sync_http_errors_carry_code_field_and_status(server, frame_json):
    with Client(server.http_url) as client:
        with pytest.raises(PosefuseError) as e:
            client.predict(bad_frame(frame_json))
        assert e.value.code == "invalid_field" and e.value.field == "calibration.intrinsic"
        assert e.value.http_status == 422 and "calibration.intrinsic" in e.value.message
        with pytest.raises(PosefuseError) as e:
            client.predict({"calibration": "nope"})
        assert e.value.http_status in (400, 422) and e.value.code in ("invalid_field", "malformed_request")
    with Client("http://127.0.0.1:9", timeout=2) as closed:
        assert not closed.ready()
        with pytest.raises(PosefuseError) as e:
            closed.predict(frame_json)
        assert e.value.code == "transport_error" and e.value.retryable


def test_async_http_client_calls_every_endpoint(server, frame_json, frames_json):
    frame = Frame.from_json(frame_json)

    async def run():
        async with AsyncClient(server.http_url) as client:
            assert await client.healthy() and await client.ready()
            manifest = await client.models()
            assert (await client.metrics()).strip()
            assert "/v1/poses" in (await client.openapi())["paths"]
            response = await client.predict(frame)
            check_pose(response, frame, manifest)
            # Concurrent calls on one client.
            many = await asyncio.gather(*(client.predict(frame) for _ in range(4)))
            for r in many:
                np.testing.assert_allclose(r.persons[0].keypoints_3d, response.persons[0].keypoints_3d, atol=1e-5)

            async def frames():
                for f in frames_json:
                    yield f
                yield bad_frame(frames_json[0])

            results = [r async for r in client.predict_batch(frames(), chunk_size=3)]
            assert [r.index for r in results] == list(range(len(frames_json) + 1))
            assert all(r.ok for r in results[:-1]) and results[-1].error.field == "calibration.intrinsic"
            report = await client.evaluate(frames_json)
            assert report["failed_frames"] == 0
            with pytest.raises(PosefuseError) as e:
                await client.predict(bad_frame(frame_json))
            assert e.value.code == "invalid_field" and e.value.http_status == 422
            return response

    response = asyncio.run(run())
    with Client(server.http_url) as client:
        sync = client.predict(frame)
    np.testing.assert_allclose(response.persons[0].keypoints_3d, sync.persons[0].keypoints_3d, atol=1e-5)


def test_numpy_image_and_points_are_served(server, frame_json):
    frame = Frame.from_json(frame_json)
    c = frame.calibration
    frame.image = np.random.default_rng(1).integers(0, 256, (c.height, c.width, 3), dtype=np.uint8)
    frame.points = np.asarray(frame.points, dtype=np.float64)
    with Client(server.http_url) as client:
        response = client.predict(frame)
        assert response.persons and response.timings.decode_ms >= 0
        lidar = client.predict(Frame(frame.calibration, frame.points, frame.persons, image=None, mode="lidar"))
    assert all(p.mode == "lidar" for p in lidar.persons)
    assert json.dumps(frame.to_json())  # serializable


def test_raw_pixel_frames_are_answered_with_their_camera(server, raw_frame_json):
    """A frame JSON with `image_rgb` (decoded pixels) keeps its camera through Frame.from_json:
    the same poses as the JSON sent as it is, in fusion, not LiDAR only."""
    frame = Frame.from_json(raw_frame_json)
    assert frame.image is None and frame.image_rgb is not None
    with Client(server.http_url) as client:
        response = client.predict(frame)
    raw = httpx.post(f"{server.http_url}/v1/poses", json=raw_frame_json, timeout=30).json()
    assert [p.id for p in response.persons] == [p["id"] for p in raw["persons"]]
    assert [p.mode for p in response.persons] == [p["mode"] for p in raw["persons"]]
    assert all(p.mode == "fusion" for p in response.persons), [(p.mode, p.mode_reason) for p in response.persons]
    for pose, want in zip(response.persons, raw["persons"], strict=True):
        assert np.isfinite(pose.scores).all()
        np.testing.assert_allclose(pose.keypoints_3d, [k["xyz"] for k in want["keypoints"]], atol=1e-6)
        np.testing.assert_allclose(pose.scores, [k["score"] for k in want["keypoints"]], atol=1e-6)
