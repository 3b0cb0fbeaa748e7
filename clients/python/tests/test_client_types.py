"""Offline checks of the client's request/response conversion, PNG encoder and error parsing."""

import base64
import struct
import zlib

import numpy as np
import pytest

from posefuse_client import Camera, Frame, PersonPose, PosefuseError, PoseResponse, RgbPixels, encode_png
from posefuse_client.errors import grpc_message_code
from posefuse_client.types import as_proto


def test_frame_round_trips_through_json_and_proto(frame_json):
    frame = Frame.from_json(frame_json)
    assert frame.points.ndim == 2 and frame.points.shape[1] == 3 and len(frame.points) > 0
    assert len(frame.persons) >= 2
    again = Frame.from_json(frame.to_json())
    np.testing.assert_array_equal(again.points, frame.points)
    assert again.image == frame.image and again.persons[0].box_3d == frame.persons[0].box_3d
    gt = again.persons[0].ground_truth
    assert gt is not None and gt.keypoints_3d.shape == (13, 3) and gt.visible_3d.shape == (13,)
    proto = frame.to_proto()
    assert np.frombuffer(proto.points, "<f4").reshape(-1, 3).tolist() == frame.points.tolist()
    assert proto.image == frame.image
    assert [p.id for p in proto.persons] == [p.id for p in frame.persons]
    assert proto.calibration.width == frame.calibration.width


def test_flat_points_are_read_like_encoded_ones(frame_json):
    frame = Frame.from_json(frame_json)
    flat = dict(frame_json, points=frame.points.reshape(-1).tolist())
    np.testing.assert_array_equal(Frame.from_json(flat).points, frame.points)


def test_bad_points_shape_is_refused_before_sending(frame_json):
    frame = Frame.from_json(frame_json)
    frame.points = np.zeros((4, 2), np.float32)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        frame.to_json()


def decode_png(data: bytes) -> np.ndarray:
    """A minimal PNG reader for 8-bit, filter-0 images (what encode_png writes), checking CRCs."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body)
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    w, h, depth, color, *_ = header
    channels = {0: 1, 2: 3, 6: 4}[color]
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + w * channels)
    assert depth == 8 and (raw[:, 0] == 0).all()
    return raw[:, 1:].reshape(h, w, channels)


@pytest.mark.parametrize("shape", [(5, 7, 3), (4, 3), (2, 6, 4)])
def test_encode_png_writes_the_pixels(shape):
    image = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    back = decode_png(encode_png(image))
    np.testing.assert_array_equal(back.reshape(image.shape), image)


def test_encode_png_refuses_what_it_cannot_write():
    with pytest.raises(ValueError, match="uint8"):
        encode_png(np.zeros((2, 2, 3), np.float32))
    with pytest.raises(ValueError, match="shape"):
        encode_png(np.zeros((2, 2, 2), np.uint8))


def test_array_image_is_sent_as_png(frame_json):
    frame = Frame.from_json(frame_json)
    frame.image = np.full((3, 4, 3), 7, np.uint8)
    sent = base64.b64decode(frame.to_json()["image"])
    assert sent.startswith(b"\x89PNG") and frame.to_proto().image == sent


def test_http_error_body_gives_code_field_and_status():
    body = (
        b'{"error": {"code": "invalid_field", "message": "invalid field `persons[0].id`: x",'
        b' "field": "persons[0].id"}}'
    )
    e = PosefuseError.from_http(422, body)
    assert (e.code, e.field, e.http_status) == ("invalid_field", "persons[0].id", 422)
    assert not e.retryable
    e = PosefuseError.from_http(502, b"<html>bad gateway</html>")
    assert e.code == "http_502" and "bad gateway" in e.message


def test_grpc_messages_give_back_the_json_codes():
    assert grpc_message_code("invalid field `persons[1].box_3d.width`: must be > 0", "INVALID_ARGUMENT") == (
        "invalid_field",
        "persons[1].box_3d.width",
    )
    assert grpc_message_code("server overloaded: the request queue is full", "RESOURCE_EXHAUSTED") == (
        "overloaded",
        None,
    )
    assert grpc_message_code("something new", "INTERNAL") == ("internal", None)
    assert PosefuseError.from_grpc("UNAVAILABLE", "not ready: warming up").retryable


def test_response_without_camera_has_nan_uv_and_scores():
    kp = {"name": "nose", "waymo_type": 1, "xyz": [1.0, 2.0, 3.0], "uv": None, "score": None}
    body = {
        "model": {"name": "default", "version": "0.2.0"},
        "persons": [{"id": "a", "mode": "lidar", "mode_reason": "r", "num_points": 5, "keypoints": [kp] * 13}],
        "timings": {"decode_ms": 1, "preprocess_ms": 2, "queue_ms": 0, "inference_ms": 3, "total_ms": 6},
    }
    r = PoseResponse.from_json(body)
    p = r.person("a")
    assert p.keypoints_3d.shape == (13, 3) and np.isnan(p.keypoints_2d).all() and np.isnan(p.scores).all()
    assert r.timings.total_ms == 6 and r.skipped == []
    with pytest.raises(KeyError):
        r.person("b")


def test_a_frame_of_several_cameras_converts_to_json_and_proto(frame_json):
    single = Frame.from_json(frame_json)
    cameras = [Camera("front", single.calibration, single.image), Camera("left", single.calibration, b"\x89PNG")]
    frame = Frame(None, single.points, single.persons, cameras=cameras)
    frame.persons[0].camera = "left"
    body = frame.to_json()
    assert "calibration" not in body and "image" not in body
    assert [c["name"] for c in body["cameras"]] == ["front", "left"]
    assert body["persons"][0]["camera"] == "left" and "camera" not in body["persons"][1]
    again = Frame.from_json(body)
    assert again.calibration is None and again.cameras == cameras and again.persons[0].camera == "left"
    proto = frame.to_proto()
    assert not proto.HasField("calibration") and proto.image == b""
    assert [(c.name, c.image) for c in proto.cameras] == [("front", single.image), ("left", b"\x89PNG")]
    assert proto.cameras[1].calibration.width == single.calibration.width
    assert proto.persons[0].camera == "left" and proto.persons[1].camera == ""


def test_the_camera_a_person_was_seen_with_is_read_back():
    pose = {"id": "p", "camera": "left", "mode": "fusion", "mode_reason": "", "num_points": 3, "keypoints": []}
    assert PersonPose.from_json(pose).camera == "left"
    assert PersonPose.from_json(dict(pose, camera=None)).camera is None


def raw_pixels(width: int, height: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def test_image_rgb_is_read_and_sent_as_the_same_raw_pixels(frame_json):
    c = frame_json["calibration"]
    pixels = raw_pixels(c["width"], c["height"])
    image_rgb = {"width": c["width"], "height": c["height"], "b64": base64.b64encode(pixels.tobytes()).decode()}
    body = {k: v for k, v in frame_json.items() if k != "image"} | {"image_rgb": image_rgb}

    frame = Frame.from_json(body)
    assert frame.image is None and frame.image_rgb == RgbPixels(c["width"], c["height"], pixels.tobytes())
    np.testing.assert_array_equal(frame.image_rgb.to_array(), pixels)
    # JSON: the pixels go out as given (not re-encoded), and no encoded image with them.
    sent = frame.to_json()
    assert sent["image_rgb"] == image_rgb and "image" not in sent
    assert Frame.from_json(sent).image_rgb == frame.image_rgb
    # gRPC: the same bytes in image_rgb with their size; a dict in the JSON form converts the same.
    for proto in (frame.to_proto(), as_proto(body)):
        assert proto.image == b"" and proto.image_rgb == pixels.tobytes()
        assert (proto.image_rgb_width, proto.image_rgb_height) == (c["width"], c["height"])


def test_image_rgb_of_each_camera_is_kept(frame_json):
    single = Frame.from_json(frame_json)
    c = single.calibration
    rgb = RgbPixels.from_array(raw_pixels(c.width, c.height, seed=1))
    frame = Frame(None, single.points, single.persons,
                  cameras=[Camera("front", c, single.image), Camera("left", c, image_rgb=rgb)])
    body = frame.to_json()
    assert "image_rgb" not in body["cameras"][0] and "image" not in body["cameras"][1]
    assert body["cameras"][1]["image_rgb"] == rgb.to_json()
    again = Frame.from_json(body)
    assert again.cameras == frame.cameras and again.cameras[1].image is None
    proto = frame.to_proto()
    assert proto.cameras[0].image == single.image and proto.cameras[0].image_rgb == b""
    left = proto.cameras[1]
    assert left.image == b"" and left.image_rgb == rgb.pixels
    assert (left.image_rgb_width, left.image_rgb_height) == (c.width, c.height)


def test_image_rgb_of_the_wrong_size_is_refused_before_sending():
    with pytest.raises(ValueError, match="image_rgb: 5 bytes, but 2x1 RGB8 pixels are 6 bytes"):
        RgbPixels(2, 1, b"\0" * 5)
    with pytest.raises(ValueError, match=r"uint8 array \[H, W, 3\]"):
        RgbPixels.from_array(np.zeros((2, 2, 4), np.uint8))
