"""ROS 2 logs in and out, read by other people's code: the recorded drive with the official `mcap`
reader and `mcap-ros2-support` (decoding each message from the log's own definitions), the poses
log with Foxglove's published protobuf classes and the poses channel with JSON Schema; and a
round trip: the frames rebuilt here from the decoded ROS messages and sent to `POST /v1/poses`
get the poses `posefuse mcap score` wrote, within 1 mm."""

import base64
import collections
import json
import math
import urllib.request

import jsonschema
import numpy as np
import pytest
from conftest import posefuse
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoder
from mcap_ros2.decoder import DecoderFactory as Ros2Decoder

SYNC_NS = 50_000_000
PEDESTRIAN = {"pedestrian", "person", "2"}
# Waymo camera axes (x forward, y left, z up) in the optical frame (z forward, x right, y down).
WAYMO_TO_OPTICAL = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=float)


def decoded(path):
    with open(path, "rb") as f:
        yield from make_reader(f, decoder_factories=[Ros2Decoder()]).iter_decoded_messages()


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def pose_matrix(translation, rotation) -> np.ndarray:
    x, y, z, w = rotation.x, rotation.y, rotation.z, rotation.w
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = [translation.x, translation.y, translation.z]
    return m


class Tf:
    def __init__(self):
        self.parent = {}

    def add(self, msg):
        for t in msg.transforms:
            self.parent[t.child_frame_id] = (
                t.header.frame_id,
                pose_matrix(t.transform.translation, t.transform.rotation),
            )

    def to_root(self, frame):
        m = np.eye(4)
        while frame in self.parent:
            frame, link = self.parent[frame]
            m = link @ m
        return frame, m

    def lookup(self, target, source):
        (rt, t), (rs, s) = self.to_root(target), self.to_root(source)
        assert rt == rs, f"{source} and {target} are in different trees"
        return np.linalg.inv(t) @ s


def cloud_points(msg) -> np.ndarray:
    fields = {f.name: f.offset for f in msg.fields if f.datatype == 7}
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(msg.height * msg.width, msg.point_step)
    order = ">f4" if msg.is_bigendian else "<f4"
    xyz = np.stack([raw[:, fields[a] : fields[a] + 4].copy().view(order)[:, 0] for a in "xyz"], axis=1)
    return xyz[np.isfinite(xyz).all(axis=1)].astype(np.float64)


def nearest(items, at):
    within = [(abs(t - at), t, m) for t, m in items if abs(t - at) <= SYNC_NS]
    return min(within, key=lambda x: x[0])[2] if within else None


def frames_of(path) -> dict[str, dict]:
    """The requests of a log's frames, built from the decoded messages as docs/ROS.md says."""
    tf, infos = Tf(), {}
    images, clouds, boxes = collections.defaultdict(list), [], []
    for schema, channel, _, msg in decoded(path):
        if schema.name == "tf2_msgs/msg/TFMessage":
            tf.add(msg)
        elif schema.name == "sensor_msgs/msg/CameraInfo":
            infos[msg.header.frame_id] = msg
        elif schema.name == "sensor_msgs/msg/CompressedImage":
            images[channel.topic].append((stamp_ns(msg.header), msg))
        elif schema.name == "sensor_msgs/msg/PointCloud2":
            clouds.append((stamp_ns(msg.header), msg))
        elif schema.name == "vision_msgs/msg/Detection3DArray":
            boxes.append((stamp_ns(msg.header), msg))
    out = {}
    for at, b in boxes:
        base = b.header.frame_id
        cloud = nearest(clouds, at)
        m = tf.lookup(base, cloud.header.frame_id)
        pts = cloud_points(cloud) @ m[:3, :3].T + m[:3, 3]
        cameras = []
        for topic, msgs in sorted(images.items()):
            img = nearest(msgs, at)
            info = infos[img.header.frame_id]
            e = tf.lookup(base, img.header.frame_id) @ WAYMO_TO_OPTICAL
            k, d = info.k, list(info.d) + [0.0] * (5 - len(info.d))
            cameras.append(
                {
                    "name": topic,
                    "image": base64.b64encode(bytes(img.data)).decode(),
                    "calibration": {
                        "intrinsic": [k[0], k[4], k[2], k[5], *d[:5]],
                        "extrinsic": e.flatten().tolist(),
                        "width": info.width,
                        "height": info.height,
                    },
                }
            )
        persons = []
        for det in b.detections:
            if not any(r.hypothesis.class_id.lower() in PEDESTRIAN for r in det.results):
                continue
            c, q = det.bbox.center.position, det.bbox.center.orientation
            yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
            s = det.bbox.size
            box = {
                "center_x": c.x,
                "center_y": c.y,
                "center_z": c.z,
                "length": s.x,
                "width": s.y,
                "height": s.z,
                "heading": yaw,
            }
            persons.append({"id": det.id, "box_3d": box})
        if persons:
            out[str(at)] = {
                "frame_id": str(at),
                "cameras": cameras,
                "points": {"b64": base64.b64encode(pts.astype("<f4").tobytes()).decode()},
                "persons": persons,
            }
    return out


def post_poses(server, frame: dict) -> dict:
    req = urllib.request.Request(
        f"{server.http_url}/v1/poses", data=json.dumps(frame).encode(), headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=120) as r:
        return json.loads(r.read())


@pytest.fixture(scope="module")
def scored(drive, server, tmp_path_factory):
    out = tmp_path_factory.mktemp("poses") / "poses.mcap"
    p = posefuse("mcap", "score", "--in", str(drive), "--out", str(out), "--server", server.http_url)
    return out, json.loads(p.stdout)


def test_the_recorded_log_decodes_with_the_official_ros2_reader(drive):
    topics = collections.Counter()
    for schema, channel, message, msg in decoded(drive):
        assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
        topics[schema.name] += 1
        if schema.name == "sensor_msgs/msg/CameraInfo":
            assert msg.distortion_model == "plumb_bob" and len(msg.d) == 5 and msg.k[8] == 1.0
            assert list(msg.p[:3]) == list(msg.k[:3])
        if schema.name == "sensor_msgs/msg/PointCloud2":
            assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity"]
            assert msg.row_step == msg.point_step * msg.width and len(msg.data) == msg.row_step
        if schema.name == "sensor_msgs/msg/CompressedImage":
            assert msg.format == "jpeg" and bytes(msg.data[:2]) == b"\xff\xd8"
            assert message.log_time == stamp_ns(msg.header)
    assert topics["tf2_msgs/msg/TFMessage"] == 1
    assert topics["vision_msgs/msg/Detection3DArray"] == 5
    assert topics["sensor_msgs/msg/CompressedImage"] == 5 * 5 == topics["sensor_msgs/msg/CameraInfo"]


def test_every_output_message_decodes_with_foxglove_schemas_as_published(scored):
    out, summary = scored
    assert summary["frames"] == summary["frames_answered"] == 5
    assert summary["persons"] > 0 and summary["failed_requests"] == 0
    published = {"foxglove.SceneUpdate": SceneUpdate, "foxglove.ImageAnnotations": ImageAnnotations}
    seen = collections.Counter()
    with open(out, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            seen[schema.name] += 1
            if schema.name in published:
                # and the decoder that reads the log's own embedded descriptors
                msg = ProtobufDecoder().decoder_for(channel.message_encoding, schema)(message.data)
                assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
                # Foxglove's own classes read every field we wrote, and write back the same bytes
                theirs = published[schema.name].FromString(message.data)
                assert theirs.SerializeToString() == message.data
                assert msg.SerializeToString() == message.data
            else:
                assert schema.name == "posefuse.PoseResponse" and schema.encoding == "jsonschema"
                jsonschema.Draft202012Validator(json.loads(schema.data)).validate(json.loads(message.data))
    assert seen["foxglove.SceneUpdate"] == 5
    assert seen["posefuse.PoseResponse"] == 5
    assert seen["foxglove.ImageAnnotations"] == 5 * 5


def test_skeletons_are_drawn_per_person_and_the_log_is_indexed_for_seeking(scored):
    out, _ = scored
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        poses = {}
        for _, _, message in reader.iter_messages(topics=["/posefuse/poses"]):
            poses[message.log_time] = json.loads(message.data)
        updates = [
            (m.log_time, SceneUpdate.FromString(m.data))
            for _, _, m in reader.iter_messages(topics=["/posefuse/skeletons"])
        ]
        start = sorted(poses)[2]
        later = list(reader.iter_messages(topics=["/posefuse/skeletons"], starting_at=start))
    assert len(later) == 3
    for t, u in updates:
        assert [d.type for d in u.deletions] == [SceneEntityDeletion.ALL]
        resp = poses[t]
        assert [e.id for e in u.entities] == [p["id"] for p in resp["persons"]]
        for e, p in zip(u.entities, resp["persons"], strict=True):
            assert e.frame_id == "base_link" and len(e.spheres) == 13
            for s, k in zip(e.spheres, p["keypoints"], strict=True):
                assert [s.pose.position.x, s.pose.position.y, s.pose.position.z] == k["xyz"]


def test_scored_poses_equal_v1_poses_on_the_same_frames(drive, server, scored):
    out, _ = scored
    with open(out, "rb") as f:
        written = {
            json.loads(m.data)["frame_id"]: json.loads(m.data)
            for _, _, m in make_reader(f).iter_messages(topics=["/posefuse/poses"])
        }
    frames = frames_of(drive)
    assert sorted(frames) == sorted(written)
    compared = 0
    for frame_id, frame in frames.items():
        direct = post_poses(server, frame)
        mine = {p["id"]: p for p in written[frame_id]["persons"]}
        assert sorted(mine) == sorted(p["id"] for p in direct["persons"])
        for p in direct["persons"]:
            q = mine[p["id"]]
            assert (q["mode"], q.get("camera"), q["num_points"]) == (p["mode"], p.get("camera"), p["num_points"])
            for a, b in zip(p["keypoints"], q["keypoints"], strict=True):
                assert max(abs(x - y) for x, y in zip(a["xyz"], b["xyz"], strict=True)) <= 1e-3, (
                    frame_id,
                    p["id"],
                    a["name"],
                )
            compared += 1
    assert compared >= 5


def test_a_truncated_log_scores_what_it_holds_and_says_where_it_ends(drive, tmp_path):
    cut = tmp_path / "cut.mcap"
    data = drive.read_bytes()
    cut.write_bytes(data[: len(data) * 3 // 5])
    p = posefuse("mcap", "score", "--in", str(cut), "--out", str(tmp_path / "out.mcap"), check=False)
    assert p.returncode != 0
    assert "cannot be read past message" in p.stderr and "panicked" not in p.stderr
    summary = json.loads(p.stdout)
    assert 0 < summary["frames"] < 5 and summary["log_error"]
    # what was scored is a complete, readable log
    with open(tmp_path / "out.mcap", "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages(topics=["/posefuse/poses"])) == summary["frames_answered"]


def test_the_preview_draws_the_annotations_over_their_images(drive, scored, tmp_path):
    import subprocess
    import sys

    from conftest import ROOT
    from PIL import Image

    out, _ = scored
    png = tmp_path / "preview.png"
    script = ROOT / "scripts/mcap_preview.py"
    args = ["--drive", str(drive), "--poses", str(out), "--out", str(png), "--frames", "2", "--height", "100"]
    p = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "2 images" in p.stdout
    sheet = np.asarray(Image.open(png).convert("RGB")).astype(int)
    assert sheet.shape[0] == 100
    # the bones' colour (0.1, 0.9, 0.4 in crates/tools/src/ros/viz.rs) is drawn
    bone = np.array([26, 230, 102])
    assert (np.abs(sheet - bone).max(axis=2) <= 12).sum() > 20
