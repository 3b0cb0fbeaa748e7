"""Offline checks of every manifest in deploy/.

Kubernetes kinds are validated against the official OpenAPI-derived JSON schemas shipped by
kubernetes-validate (strict: unknown fields fail), for the oldest and the newest Kubernetes minor
version this project supports. KServe's CRDs (ServingRuntime, InferenceService) are not in those
schemas: they are validated against the small JSON schema below, which holds the fields KServe
requires and the ones posefuse relies on, and their cross-references are checked. The
kustomization is checked structurally (the files it names exist).

Beyond schemas, the manifests must agree with the Dockerfile (image name, user, port, env), with
the server (its routes and flags) and with each other (selectors, names, shard counts, drain time).
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
# Server flags set in the manifests that come with the bounded-drain change; they are accepted
# before src/ declares them (the server ignores unknown POSEFUSE_* variables).
PENDING_FLAGS = {"POSEFUSE_DRAIN_TIMEOUT"}

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


def server_flags() -> set[str]:
    """Every environment variable the server's CLI reads (`env = "..."` in src/)."""
    return {m for p in ROOT.joinpath("src").rglob("*.rs") for m in re.findall(r'env = "([A-Z0-9_]+)"', p.read_text())}


def server_routes() -> set[str]:
    return {m for p in ROOT.joinpath("src").rglob("*.rs") for m in re.findall(r'\.route\("([^"]+)"', p.read_text())}


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
    return {e["name"]: e["value"] for e in container.get("env", [])}


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
                "InferenceService", "Job", "Kustomization"}
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
    flags = server_flags()
    containers = posefuse_containers()
    assert len(containers) == 2, "the Deployment and the ServingRuntime run the server"
    for spec, c in containers:
        assert c.get("args", ["serve"]) == ["serve"]
        assert [p["containerPort"] for p in c["ports"]] == [df["port"]]
        sc = {**spec.get("securityContext", {}), **c.get("securityContext", {})}
        assert sc["runAsUser"] == df["uid"] and sc["runAsNonRoot"] is True
        assert sc["readOnlyRootFilesystem"] is True and sc["allowPrivilegeEscalation"] is False
        env = env_of(c)
        for name in env:
            assert name in df["env"] or name in flags or name in PENDING_FLAGS, f"{name} is not a server setting"
        for name in ("ORT_DYLIB_PATH", "POSEFUSE_ADDR", "RUST_LOG"):
            assert env[name] == df["env"][name].strip('"'), name
        assert env["POSEFUSE_ADDR"].endswith(f":{df['port']}")
        assert "POSEFUSE_DRAIN_TIMEOUT" in env
        assert c["resources"]["limits"]["memory"] and c["resources"]["requests"]["cpu"]
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
    assert runtime["readinessProbe"]["httpGet"]["path"] in routes


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
    pdb = one("PodDisruptionBudget")
    assert pdb["spec"]["minAvailable"] < hpa["spec"]["minReplicas"] <= deployment["spec"]["replicas"]


def test_batch_job_shards_match_and_reach_the_service():
    job, service = one("Job"), one("Service")
    spec = job["spec"]
    assert spec["completionMode"] == "Indexed"
    env = env_of(spec["template"]["spec"]["containers"][0])
    assert spec["completions"] == spec["parallelism"] == int(env["NUM_SHARDS"])
    url = re.fullmatch(r"http://([a-z0-9-]+):(\d+)", env["POSEFUSE_URL"])
    assert url and url.group(1) == service["metadata"]["name"]
    assert int(url.group(2)) in [p["port"] for p in service["spec"]["ports"]]
    kustomization = one("Kustomization")
    base = DEPLOY / "batch"
    assert all((base / r).is_file() for r in kustomization["resources"])
    (generator,) = kustomization["configMapGenerator"]
    assert all((base / f).is_file() for f in generator["files"])
    volumes = {v["name"]: v for v in spec["template"]["spec"]["volumes"]}
    assert volumes["scripts"]["configMap"]["name"] == generator["name"]
    command = spec["template"]["spec"]["containers"][0]["command"]
    assert command[-1] == "/scripts/" + generator["files"][0]
