#!/usr/bin/env bash
# Regenerates posefuse_client/posefuse.binpb, the compiled descriptor of proto/posefuse.proto that
# the client builds its gRPC messages from (any protobuf runtime >= 4.25 reads it; generated
# *_pb2.py modules would pin the runtime to the generator's version). Needs grpcio-tools (in
# models-export/requirements.txt); tests/test_client_stubs.py fails when the file is stale.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-../../.venv/bin/python}
"$PY" -m grpc_tools.protoc -I../../proto --descriptor_set_out=posefuse_client/posefuse.binpb posefuse.proto
