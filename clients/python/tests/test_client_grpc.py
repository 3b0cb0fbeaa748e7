"""The gRPC clients, sync and async, end to end against a live `posefuse serve`; their answers
equal the HTTP API's for the same frame."""

import asyncio
import copy

import numpy as np
import pytest

from posefuse_client import AsyncGrpcClient, Client, Frame, GrpcClient, PosefuseError


def bad_frame(frame_json: dict) -> dict:
    bad = copy.deepcopy(frame_json)
    bad["calibration"]["intrinsic"] = bad["calibration"]["intrinsic"][:3]
    return bad


def assert_same_poses(a, b) -> None:
    assert [p.id for p in a.persons] == [p.id for p in b.persons]
    assert [p.mode for p in a.persons] == [p.mode for p in b.persons]
    assert [s.id for s in a.skipped] == [s.id for s in b.skipped]
    for pa, pb in zip(a.persons, b.persons, strict=True):
        assert pa.names == pb.names and pa.num_points == pb.num_points
        np.testing.assert_allclose(pa.keypoints_3d, pb.keypoints_3d, atol=1e-5)
        both = ~np.isnan(pa.keypoints_2d) & ~np.isnan(pb.keypoints_2d)
        np.testing.assert_allclose(pa.keypoints_2d[both], pb.keypoints_2d[both], atol=1e-3)
        assert (pa.box_2d is None) == (pb.box_2d is None)
        if pa.box_2d is not None:
            np.testing.assert_allclose(
                [pa.box_2d.center_x, pa.box_2d.center_y, pa.box_2d.width, pa.box_2d.height],
                [pb.box_2d.center_x, pb.box_2d.center_y, pb.box_2d.width, pb.box_2d.height],
                atol=1e-9,
            )
        assert (pa.facing is None) == (pb.facing is None)
        if pa.facing is not None:
            assert abs(pa.facing.yaw - pb.facing.yaw) < 1e-6 and abs(pa.facing.confidence - pb.facing.confidence) < 1e-6
    assert any(p.facing is not None for p in a.persons)
    assert any(p.box_2d is not None for p in a.persons)
    assert a.model_name == b.model_name and a.model_version == b.model_version


def test_sync_grpc_client_matches_http(server, frame_json, frames_json):
    frame = Frame.from_json(frame_json)
    with Client(server.http_url) as http:
        expected = http.predict(frame)
        expected_all = [http.predict(f) for f in frames_json]
    with GrpcClient(server.grpc_target) as client:
        assert client.ready()
        assert client.ready("posefuse.v1.Posefuse")
        got = client.predict(frame)
        assert_same_poses(got, expected)
        assert got.frame_id == frame.frame_id and got.timings.total_ms > 0

        inputs = [*frames_json[:1], bad_frame(frames_json[0]), *frames_json[1:]]
        results = list(client.predict_stream(iter(inputs)))
    assert [r.index for r in results] == list(range(len(inputs)))
    bad = results[1]
    assert not bad.ok and bad.error.code == "invalid_field" and bad.error.field == "calibration.intrinsic"
    for r, e in zip([results[0], *results[2:]], expected_all, strict=True):
        assert_same_poses(r.response, e)



def test_raw_pixel_frames_keep_their_camera_over_grpc(server, raw_frame_json):
    """`image_rgb` travels as the proto's raw pixel bytes, from a Frame or a dict in the JSON form."""
    with Client(server.http_url) as http:
        expected = http.predict(raw_frame_json)
    assert all(p.mode == "fusion" for p in expected.persons)
    with GrpcClient(server.grpc_target) as client:
        assert_same_poses(client.predict(Frame.from_json(raw_frame_json)), expected)
        assert_same_poses(client.predict(raw_frame_json), expected)

def test_sync_grpc_errors_carry_code_field_and_status(server, frame_json):
    with GrpcClient(server.grpc_target) as client:
        with pytest.raises(PosefuseError) as e:
            client.predict(bad_frame(frame_json))
    assert e.value.grpc_status == "INVALID_ARGUMENT"
    assert e.value.code == "invalid_field" and e.value.field == "calibration.intrinsic"
    with GrpcClient("127.0.0.1:9", timeout=2) as closed:
        assert not closed.ready()
        with pytest.raises(PosefuseError) as e:
            closed.predict(frame_json)
    assert e.value.code == "transport_error" and e.value.retryable


def test_async_grpc_client_matches_sync(server, frame_json, frames_json):
    frame = Frame.from_json(frame_json)
    with GrpcClient(server.grpc_target) as sync:
        expected = sync.predict(frame)

    async def run():
        async with AsyncGrpcClient(server.grpc_target) as client:
            assert await client.ready()
            got = await client.predict(frame)
            assert_same_poses(got, expected)
            many = await asyncio.gather(*(client.predict(frame_json) for _ in range(4)))
            for r in many:
                assert_same_poses(r, expected)

            async def frames():
                yield bad_frame(frame_json)
                for f in frames_json:
                    yield f

            results = [r async for r in client.predict_stream(frames())]
            assert [r.index for r in results] == list(range(len(frames_json) + 1))
            assert results[0].error.field == "calibration.intrinsic" and all(r.ok for r in results[1:])
            with pytest.raises(PosefuseError) as e:
                await client.predict(bad_frame(frame_json))
            assert e.value.grpc_status == "INVALID_ARGUMENT" and e.value.field == "calibration.intrinsic"

    asyncio.run(run())
