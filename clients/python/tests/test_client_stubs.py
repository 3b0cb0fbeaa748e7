"""The committed descriptor (posefuse_client/posefuse.binpb) is proto/posefuse.proto as it is
(regenerate with clients/python/generate-descriptor.sh when this fails), and the messages built from it
carry the fields the client sets."""

import subprocess
import sys
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2

from posefuse_client import _proto

ROOT = Path(__file__).resolve().parents[3]
COMMITTED = ROOT / "clients" / "python" / "posefuse_client" / "posefuse.binpb"


def test_committed_descriptor_matches_the_proto(tmp_path):
    pytest.importorskip("grpc_tools", reason="grpcio-tools is not installed (models-export/requirements.txt)")
    out = tmp_path / "posefuse.binpb"
    subprocess.run(
        [sys.executable, "-m", "grpc_tools.protoc", f"-I{ROOT / 'proto'}", f"--descriptor_set_out={out}",
         "posefuse.proto"],
        check=True,
    )
    fresh = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes())
    assert descriptor_pb2.FileDescriptorSet.FromString(COMMITTED.read_bytes()) == fresh


def test_messages_and_methods_come_from_the_descriptor():
    assert [s.name for s in _proto.FILE.services_by_name.values()] == ["Posefuse"]
    methods = _proto.FILE.services_by_name["Posefuse"].methods_by_name
    assert set(methods) == {"Predict", "PredictStream"}
    assert methods["PredictStream"].client_streaming and methods["PredictStream"].server_streaming
    request = _proto.PredictRequest(frame_id="f", points=b"\0" * 12, mode=2)
    assert _proto.PredictRequest.FromString(request.SerializeToString()).frame_id == "f"
    health = _proto.HealthCheckResponse.FromString(bytes([8, 1]))
    assert health.status == _proto.SERVING
