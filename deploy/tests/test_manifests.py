"""Offline checks of every manifest in deploy/.

Kubernetes kinds are validated against the official OpenAPI-derived JSON schemas shipped by
kubernetes-validate (strict: unknown fields fail), for the oldest and the newest Kubernetes minor
version this project supports. KServe's CRDs (ServingRuntime, InferenceService) are not in those
schemas: they are validated against the small JSON schema below, which holds the fields KServe
requires and the ones posefuse relies on, and their cross-references are checked. The
kustomization is checked structurally (the files it names exist).

Beyond schemas, the manifests must agree with the Dockerfile (image name, user, port, env), with
the server (its routes and flags) and with each other (selectors, names, shard counts, drain time),
and hold what an operator relies on: pods spread over nodes, no replica count beside the HPA, one
h2c port and no admin port in the Service, explicit CPU and memory, probes, and a memory limit that
covers the worst case the server's admission flags allow (the arithmetic of docs/DEPLOY.md).
The batch Job's own checks are in test_batch_job.py.
"""

from __future__ import annotations

import re
from pathlib import Path

import jsonschema
import kubernetes_validate
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
# Oldest supported (Indexed Jobs' backoffLimitPerIndex is beta, on by default, since 1.29) and newest.
K8S_VERSIONS = ["1.29.0", kubernetes_validate.utils.latest_version()]
# Memory arithmetic (docs/DEPLOY.md, "Memory"). The resident size under load, measured: 279 MB peak
# at 64 clients, release build, default flags on two cores (two inference workers, each with its
# sessions), the default bundle 0.6.0, the system allocator (BENCHMARKS.md, "Two inference workers
# on two cores"). More workers hold more sessions, so the manifests must state the measured count.
MEASURED_RESIDENT = 279_000_000
MEASURED_WORKERS = 2
# Bytes per pixel of the largest decode: a 16-bit RGBA PNG (8) and its RGB8 copy (3), both alive.
DECODE_BYTES_PER_PIXEL = 8 + 3
MIB = 1024 * 1024

KSERVE_CONTAINER = {
    "type": "object",
    "required": ["name", "image"],
    "properties": {
        "name": {"type": "string"},
        "image": {"type": "string"},
        "args": {"type": "array", "items": {"type": "string"}},
        "env": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["name", "value"],
                "properties": {"name": {"type": "string"}, "value": {"type": "string"}},
            },
        },
        "ports": {
            "type": "array",
            "maxItems": 1,
            "items": {
                "type": "object",
                "required": ["containerPort"],
                "properties": {
                    "name": {"enum": ["h2c", "http1"]},
                    "containerPort": {"type": "integer"},
                    "protocol": {"enum": ["TCP"]},
                },
            },
        },
    },
}
KSERVE_SCHEMAS = {
    ("serving.kserve.io/v1alpha1", "ServingRuntime"): {
        "type": "object",
        "required": ["apiVersion", "kind", "metadata", "spec"],
        "properties": {
            "metadata": {"type": "object", "required": ["name"]},
            "spec": {
                "type": "object",
                "required": ["supportedModelFormats", "containers"],
                "properties": {
                    "supportedModelFormats": {
                        "type": "array",
                        "minItems": 1,
                        "items": {
                            "type": "object",
                            "required": ["name"],
                            "properties": {
                                "name": {"type": "string"},
                                "version": {"type": "string"},
                                "autoSelect": {"type": "boolean"},
                            },
                        },
                    },
                    "protocolVersions": {
                        "type": "array",
                        "items": {"enum": ["v1", "v2", "grpc-v1", "grpc-v2"]},
                    },
                    "multiModel": {"type": "boolean"},
                    "containers": {"type": "array", "minItems": 1, "items": KSERVE_CONTAINER},
                },
            },
        },
    },
    ("serving.kserve.io/v1beta1", "InferenceService"): {
        "type": "object",
        "required": ["apiVersion", "kind", "metadata", "spec"],
        "properties": {
            "metadata": {"type": "object", "required": ["name"]},
            "spec": {
                "type": "object",
                "required": ["predictor"],
                "properties": {
                    "predictor": {
                        "type": "object",
                        "required": ["model"],
                        "properties": {
                            "minReplicas": {"type": "integer", "minimum": 0},
                            "containerConcurrency": {"type": "integer", "minimum": 0},
                            "maxReplicas": {"type": "integer", "minimum": 1},
                            "terminationGracePeriodSeconds": {"type": "integer", "minimum": 0},
                            "model": {
                                "type": "object",
                                "required": ["modelFormat"],
                                "properties": {
                                    "modelFormat": {
                                        "type": "object",
                                        "required": ["name"],
                                        "properties": {
                                            "name": {"type": "string"},
                                            "version": {"type": "string"},
                                        },
                                    },
                                    "runtime": {"type": "string"},
                                    "protocolVersion": {"enum": ["v1", "v2", "grpc-v2"]},
                                    "storageUri": {"type": "string", "pattern": "^[a-z0-9]+://"},
                                },
                            },
                        },
                    },
                },
            },
        },
    },
}


def load_documents() -> list[tuple[Path, dict]]:
    docs = []
    for path in sorted(DEPLOY.rglob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc is not None:
                docs.append((path, doc))
    return docs


DOCS = load_documents()


def one(kind: str) -> dict:
    found = [doc for _, doc in DOCS if doc["kind"] == kind]
    assert len(found) == 1, f"expected one {kind}, found {len(found)}"
    return found[0]


def dockerfile() -> dict:
    """Image name, user id, port and ENV of the repository's Dockerfile."""
    text = ROOT.joinpath("Dockerfile").read_text()
    runtime = text.split("\nFROM debian", 1)[1]
    env = dict(re.findall(r"\b([A-Z][A-Z0-9_]+)=(\S+)", runtime.split("ENV", 1)[1].split("\nUSER", 1)[0]))
    return {
        "image": re.search(r"docker build -t (\S+) \.", text).group(1),
        "uid": int(re.search(r"useradd --uid (\d+)", text).group(1)),
        "port": int(re.search(r"^EXPOSE (\d+)", text, re.M).group(1)),
        "env": env,
    }


def rust_sources() -> list[Path]:
    """The Rust sources of the binary (src/) and of the workspace's crates (crates/)."""
    return [p for d in ("src", "crates") for p in ROOT.joinpath(d).rglob("*.rs")]


def server_flags() -> set[str]:
    """Every environment variable the server's CLI reads (`env = "..."` in src/)."""
    return {m for p in rust_sources() for m in re.findall(r'env = "([A-Z0-9_]+)"', p.read_text())}


def server_routes() -> set[str]:
    return {m for p in rust_sources() for m in re.findall(r'\.route\("([^"]+)"', p.read_text())}


def pod_spec(doc: dict) -> dict:
    if doc["kind"] == "ServingRuntime":
        return doc["spec"]
    return doc["spec"]["template"]["spec"]


def posefuse_containers() -> list[tuple[dict, dict]]:
    """(pod spec, container) of every container that runs the server image."""
    image = dockerfile()["image"]
    out = []
    for _, doc in DOCS:
        if doc["kind"] in ("Deployment", "ServingRuntime", "Job"):
            spec = pod_spec(doc)
            out += [(spec, c) for c in spec["containers"] if c["image"].split(":")[0] == image]
    return out


def env_of(container: dict) -> dict[str, str]:
    """The container's literal env values (`valueFrom` entries map to None)."""
    return {e["name"]: e.get("value") for e in container.get("env", [])}


def cli_flags(*structs: str) -> set[str]:
    """The `--long` flags of clap argument structs in src/cli/ (flattened structs included)."""
    text = "".join(p.read_text() for p in sorted(ROOT.joinpath("src/cli").glob("*.rs")))
    flags: set[str] = set()
    for name in structs:
        body = re.search(r"pub struct " + name + r" \{(.*?)\n\}", text, re.S)
        assert body, f"no struct {name} in src/cli"
        for attr, field in re.findall(r"#\[arg\(([^\n]*)\)\]\s*pub (\w+):", body.group(1)):
            long = re.search(r'\blong\b(?:\s*=\s*"([^"]+)")?', attr)
            if long:
                flags.add("--" + (long.group(1) or field.replace("_", "-")))
        for flattened in re.findall(r"#\[command\(flatten\)\]\s*pub \w+: (?:[\w:]+::)?(\w+),", body.group(1)):
            flags |= cli_flags(flattened)
    return flags


def parse_flags(args: list[str]) -> dict[str, str | None]:
    """`--flag value` and `--flag=value` pairs of a command line (None for a flag alone)."""
    out: dict[str, str | None] = {}
    i = 0
    while i < len(args):
        flag, eq, value = args[i].partition("=")
        assert flag.startswith("--"), f"{args[i]!r} is not a flag"
        if not eq and i + 1 < len(args) and not args[i + 1].startswith("--"):
            value, i = args[i + 1], i + 1
        out[flag] = value if (eq or value) else None
        i += 1
    return out


def server_containers() -> list[tuple[dict, dict]]:
    """(pod spec, container) of every container that runs `posefuse serve`."""
    return [(s, c) for s, c in posefuse_containers() if c.get("args", ["serve"])[0] == "serve"]


def quantity(q: str | int) -> float:
    """A Kubernetes quantity ("1Gi", "500m", "2") as a number (bytes, cores)."""
    q = str(q)
    units = {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40, "k": 1e3, "M": 1e6, "G": 1e9, "m": 1e-3}
    for suffix, factor in units.items():
        if q.endswith(suffix):
            return float(q[: -len(suffix)]) * factor
    return float(q)


def rust_const(path: str, pattern: str) -> int:
    return int(re.search(pattern, ROOT.joinpath(path).read_text()).group(1).replace("_", ""))


def worst_case_memory(container: dict) -> dict[str, float]:
    """The memory arithmetic of docs/DEPLOY.md for a server container's flags, in bytes."""
    env = env_of(container)
    permits = int(env["POSEFUSE_DECODE_PERMITS"])
    waiting = int(env["POSEFUSE_ADMISSION_QUEUE"])
    body = int(env["POSEFUSE_BODY_LIMIT"])
    assert permits > 0 and waiting > 0 and body > 0, "0 would size them from the node's cores"
    assert env.get("POSEFUSE_WORKERS") == str(MEASURED_WORKERS), "the resident size was measured with these workers"
    # The server keeps a waiting line by default; what its frames hold is not in this arithmetic.
    assert env.get("POSEFUSE_ADMISSION_WAIT_MS") == "0", "the waiting line must be off (stated) here"
    persons = int(
        env.get("POSEFUSE_MAX_PERSONS")
        or rust_const("crates/serve/src/service/predict.rs", r"MAX_PERSONS: usize = ([\d_]+)")
    )
    points = int(
        env.get("POSEFUSE_MAX_POINTS") or rust_const("crates/serve/src/service/limits.rs", r"max_points: ([\d_]+)")
    )
    manifest = yaml.safe_load(ROOT.joinpath("models/default/manifest.json").read_text())
    side = manifest["preprocessing"]["image_size"]
    crops = persons * side * side * 3 * 4  # float32 CHW crop per person
    # An admitted frame: its body as received and the frame parsed from it (at most twice the body:
    # a flat point array of one-digit numbers turns 2 bytes of text into a 4-byte float), and once
    # pre-processed, every person's crop until inference.
    per_frame = 3 * body + crops
    # A decode permit: one decoded image at a time (its declared size, which the flag bounds), the
    # points copied twice (decoded, then as triples), the image or point bytes decoded from base64.
    image_pixels = int(env["POSEFUSE_MAX_IMAGE_PIXELS"])
    assert image_pixels > 0, "the server refuses 0 at start"
    per_permit = image_pixels * DECODE_BYTES_PER_PIXEL + 2 * points * 12 + 0.75 * body
    total = MEASURED_RESIDENT + (permits + waiting) * per_frame + permits * per_permit
    return {"frames": permits + waiting, "per_frame": per_frame, "per_permit": per_permit, "total": total}


@pytest.mark.parametrize("version", K8S_VERSIONS)
@pytest.mark.parametrize(
    "path,doc",
    [(p, d) for p, d in DOCS if not d["apiVersion"].startswith(("serving.kserve.io/", "kustomize.config.k8s.io/"))],
    ids=lambda v: v.name if isinstance(v, Path) else v.get("kind") if isinstance(v, dict) else None,
)
def test_kubernetes_kinds_validate_against_the_official_schemas(path, doc, version):
    kubernetes_validate.validate(doc, version, strict=True)


def test_every_manifest_is_checked_and_every_kind_is_there():
    kinds = {doc["kind"] for _, doc in DOCS}
    expected = {"Deployment", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget", "ServingRuntime",
                "InferenceService", "Job", "PersistentVolumeClaim", "Kustomization"}
    assert kinds == expected


@pytest.mark.parametrize("kind", ["ServingRuntime", "InferenceService"])
def test_kserve_resources_validate_against_their_schema(kind):
    doc = one(kind)
    jsonschema.validate(doc, KSERVE_SCHEMAS[(doc["apiVersion"], kind)])


def test_kserve_schema_rejects_what_kserve_would():
    runtime = one("ServingRuntime")
    schema = KSERVE_SCHEMAS[(runtime["apiVersion"], "ServingRuntime")]
    broken = {**runtime, "spec": {**runtime["spec"], "protocolVersions": ["v3"]}}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(broken, schema)
    no_formats = {**runtime, "spec": {k: v for k, v in runtime["spec"].items() if k != "supportedModelFormats"}}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(no_formats, schema)


def test_kserve_service_uses_the_runtime_for_v2_and_the_bundle_format():
    runtime, isvc = one("ServingRuntime"), one("InferenceService")
    model = isvc["spec"]["predictor"]["model"]
    assert model["runtime"] == runtime["metadata"]["name"]
    assert model["protocolVersion"] == "v2"
    assert {"v2", "grpc-v2"} <= set(runtime["spec"]["protocolVersions"])
    formats = {(f["name"], f.get("version")) for f in runtime["spec"]["supportedModelFormats"]}
    assert (model["modelFormat"]["name"], model["modelFormat"].get("version")) in formats
    manifest = yaml.safe_load(ROOT.joinpath("models/default/manifest.json").read_text())
    assert model["modelFormat"]["version"] == str(manifest["format_version"])
    container = runtime["spec"]["containers"][0]
    assert container["name"] == "kserve-container"
    assert env_of(container)["POSEFUSE_MODEL_DIR"] == "/mnt/models", "KServe mounts storageUri there"


def test_server_containers_match_the_dockerfile():
    df = dockerfile()
    env_flags = server_flags()
    serve_flags = cli_flags("ServeArgs")
    containers = server_containers()
    assert len(containers) == 2, "the Deployment and the ServingRuntime run the server"
    for spec, c in containers:
        args = c.get("args", ["serve"])
        assert args[0] == "serve"
        for flag in parse_flags(args[1:]):
            assert flag in serve_flags, f"{flag} is not a flag of posefuse serve"
        assert [p["containerPort"] for p in c["ports"]] == [df["port"]]
        sc = {**spec.get("securityContext", {}), **c.get("securityContext", {})}
        assert sc["runAsUser"] == df["uid"] and sc["runAsNonRoot"] is True
        assert sc["readOnlyRootFilesystem"] is True and sc["allowPrivilegeEscalation"] is False
        env = env_of(c)
        for name in env:
            assert name in df["env"] or name in env_flags, f"{name} is not a server setting"
        for name in ("ORT_DYLIB_PATH", "POSEFUSE_ADDR", "RUST_LOG"):
            assert env[name] == df["env"][name].strip('"'), name
        assert env["POSEFUSE_ADDR"].endswith(f":{df['port']}")
        assert "POSEFUSE_DRAIN_TIMEOUT" in env
    deployment = one("Deployment")["spec"]["template"]["spec"]["containers"][0]
    assert env_of(deployment)["POSEFUSE_MODEL_DIR"] == df["env"]["POSEFUSE_MODEL_DIR"]


def test_probes_use_the_servers_health_routes():
    routes = server_routes()
    c = one("Deployment")["spec"]["template"]["spec"]["containers"][0]
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert c["livenessProbe"]["httpGet"]["path"] == "/healthz"
    assert c["startupProbe"]["httpGet"]["path"] == "/readyz"
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert c[probe]["httpGet"]["path"] in routes
        assert c[probe]["httpGet"]["port"] in [p["name"] for p in c["ports"]]
    runtime = one("ServingRuntime")["spec"]["containers"][0]
    # The Open Inference Protocol's own health routes; Knative wants the serving port itself.
    assert runtime["startupProbe"]["httpGet"]["path"] == "/v2/health/ready"
    assert runtime["readinessProbe"]["httpGet"]["path"] == "/v2/health/ready"
    assert runtime["livenessProbe"]["httpGet"]["path"] == "/v2/health/live"
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert runtime[probe]["httpGet"]["path"] in routes
        assert runtime[probe]["httpGet"]["port"] == runtime["ports"][0]["containerPort"]
    for container in (c, runtime):
        # Liveness never restarts a pod that is merely slow to start: the startup probe allows
        # longer than liveness does, and liveness only begins after it.
        startup = container["startupProbe"]["periodSeconds"] * container["startupProbe"]["failureThreshold"]
        live = container["livenessProbe"]["periodSeconds"] * container["livenessProbe"]["failureThreshold"]
        assert startup >= 60 and startup >= live


def test_kserve_v2_model_name_is_the_inferenceservice_name():
    runtime = one("ServingRuntime")["spec"]["containers"][0]
    flags = parse_flags(runtime["args"][1:])
    # KServe replaces {{.Name}} in the runtime's args with the InferenceService's name.
    assert flags["--model-name"] == "{{.Name}}"
    isvc = one("InferenceService")
    name = isvc["metadata"]["name"]
    assert re.fullmatch(r"[a-z0-9]([-a-z0-9]*[a-z0-9])?", name)
    comment = DEPLOY.joinpath("kserve/inferenceservice.yaml").read_text()
    assert f"/v2/models/{name}/infer" in comment and f'model_name "{name}"' in comment


def test_grace_period_covers_prestop_and_drain():
    spec = one("Deployment")["spec"]["template"]["spec"]
    c = spec["containers"][0]
    command = c["lifecycle"]["preStop"]["exec"]["command"]
    assert command[0] == "/bin/sleep"
    pre_stop = int(command[1])
    drain = int(env_of(c)["POSEFUSE_DRAIN_TIMEOUT"])
    # The readiness probe must see the 503 (and endpoints update) before the drain ends.
    assert pre_stop >= c["readinessProbe"]["periodSeconds"]
    assert spec["terminationGracePeriodSeconds"] >= pre_stop + drain + 5
    runtime = one("ServingRuntime")["spec"]["containers"][0]
    isvc = one("InferenceService")["spec"]["predictor"]
    assert isvc["terminationGracePeriodSeconds"] >= int(env_of(runtime)["POSEFUSE_DRAIN_TIMEOUT"]) + 5


def test_service_hpa_and_pdb_point_at_the_deployment():
    deployment, service = one("Deployment"), one("Service")
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert deployment["spec"]["selector"]["matchLabels"].items() <= labels.items()
    assert service["spec"]["selector"].items() <= labels.items()
    assert one("PodDisruptionBudget")["spec"]["selector"]["matchLabels"].items() <= labels.items()
    port_names = [p["name"] for p in deployment["spec"]["template"]["spec"]["containers"][0]["ports"]]
    assert all(p["targetPort"] in port_names for p in service["spec"]["ports"])
    hpa = one("HorizontalPodAutoscaler")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment",
                                             "name": deployment["metadata"]["name"]}
    assert hpa["spec"]["metrics"][0]["resource"]["name"] == "cpu"
    # CPU utilization is relative to the request: without one the HPA cannot act.
    assert deployment["spec"]["template"]["spec"]["containers"][0]["resources"]["requests"]["cpu"]
    pdb = one("PodDisruptionBudget")["spec"]
    # One eviction at a time whatever the HPA's count, never all but one.
    assert pdb.get("maxUnavailable") == 1 and "minAvailable" not in pdb
    assert hpa["spec"]["minReplicas"] >= 2


def test_no_replica_count_beside_the_hpa():
    """`kubectl apply` would reset the HPA's count to a `replicas` field; the HPA owns it."""
    deployment = one("Deployment")
    hpa_targets = [h["spec"]["scaleTargetRef"]["name"] for _, h in DOCS if h["kind"] == "HorizontalPodAutoscaler"]
    assert deployment["metadata"]["name"] in hpa_targets
    assert "replicas" not in deployment["spec"]
    assert "No `replicas`" in DEPLOY.joinpath("deployment.yaml").read_text(), "say why in a comment"


def test_pods_spread_over_nodes_and_zones():
    spec = one("Deployment")["spec"]["template"]
    labels = spec["metadata"]["labels"]
    constraints = {c["topologyKey"]: c for c in spec["spec"]["topologySpreadConstraints"]}
    node, zone = constraints["kubernetes.io/hostname"], constraints["topology.kubernetes.io/zone"]
    # Two pods on one node only when every node has one: hard on nodes, best effort on zones.
    assert node["maxSkew"] == 1 and node["whenUnsatisfiable"] == "DoNotSchedule"
    assert zone["whenUnsatisfiable"] == "ScheduleAnyway"
    # Cordoned nodes do not count as empty domains (a drain would leave the evicted pod Pending).
    assert node.get("nodeTaintsPolicy") == "Honor"
    for c in (node, zone):
        assert c["labelSelector"]["matchLabels"].items() <= labels.items()


def test_service_is_one_h2c_port_and_no_admin_port():
    service = one("Service")
    (port,) = service["spec"]["ports"]
    # HTTP/1.1, h2c and gRPC share the port: gateways and meshes should speak h2c to it.
    assert port["appProtocol"] == "kubernetes.io/h2c"
    containers = [c for _, c in server_containers()]
    deployment = one("Deployment")["spec"]["template"]["spec"]["containers"][0]
    serving = [p for p in deployment["ports"] if p["name"] == port["targetPort"]]
    assert [p["containerPort"] for p in serving] == [dockerfile()["port"]] == [port["port"]]
    for c in containers:
        # The admin address (reload) is loopback-only when set, and never a declared port.
        assert len(c["ports"]) == 1
        admin = parse_flags(c["args"][1:]).get("--admin-addr") or env_of(c).get("POSEFUSE_ADMIN_ADDR")
        if admin:
            host, _, admin_port = admin.rpartition(":")
            assert host in ("127.0.0.1", "[::1]"), f"--admin-addr {admin} must be loopback"
            assert int(admin_port) not in [p["port"] for p in service["spec"]["ports"]]


def test_every_container_states_cpu_and_memory():
    for _, doc in DOCS:
        if doc["kind"] not in ("Deployment", "ServingRuntime", "Job"):
            continue
        for c in pod_spec(doc)["containers"]:
            r = c["resources"]
            for kind in ("requests", "limits"):
                assert quantity(r[kind]["cpu"]) > 0 and quantity(r[kind]["memory"]) > 0, (doc["kind"], kind)
            assert quantity(r["requests"]["memory"]) <= quantity(r["limits"]["memory"])
    for _, c in server_containers():
        r = c["resources"]
        # Whole cores: Rust's available_parallelism rounds the cgroup quota down, so 1500m would
        # size the server for one core; request = limit is what the HPA's utilization means.
        assert quantity(r["limits"]["cpu"]) == int(quantity(r["limits"]["cpu"])) == quantity(r["requests"]["cpu"])
        env = env_of(c)
        # The explicit sizing matches the cores it is given (one decode permit per core).
        assert int(env["POSEFUSE_DECODE_PERMITS"]) == int(quantity(r["limits"]["cpu"]))


@pytest.mark.parametrize("kind", ["Deployment", "ServingRuntime"])
def test_the_worst_case_the_admission_flags_allow_fits_the_memory_limit(kind):
    (container,) = [c for s, c in server_containers() if s is pod_spec(one(kind))]
    m = worst_case_memory(container)
    limit = quantity(container["resources"]["limits"]["memory"])
    assert m["total"] <= limit, f"{m['total'] / MIB:.0f} MiB worst case over the {limit / MIB:.0f} MiB limit"
    # The arithmetic written in deploy/deployment.yaml and docs/DEPLOY.md is this one.
    total = f"= {m['total'] / MIB:.0f} MiB of the"
    assert total in DEPLOY.joinpath("deployment.yaml").read_text()
    assert total in ROOT.joinpath("docs/DEPLOY.md").read_text()


def test_kserve_concurrency_keeps_bodies_within_the_arithmetic():
    """The queue-proxy lets no more requests in than the server admits frames (the rest wait in it)."""
    runtime = one("ServingRuntime")["spec"]["containers"][0]
    predictor = one("InferenceService")["spec"]["predictor"]
    assert 0 < predictor["containerConcurrency"] <= worst_case_memory(runtime)["frames"]
