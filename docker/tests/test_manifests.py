"""Offline checks of docker/k8s and docker/compose.yaml: no cluster and no Docker engine needed.

Every Kubernetes object (the base, the GPU overlay as kustomize renders it, the RayJob's pod
templates, the results volume) is validated strictly (unknown fields rejected) against the
Kubernetes JSON schemas that kubernetes-validate ships, for the oldest and the newest Kubernetes
versions named below. The RayJob itself is checked against a schema written here from KubeRay's
RayJob CRD (ray.io/v1, KubeRay v1.7.0): its field names and the types of the fields we use (the
CRD itself, 1.1 MB of generated YAML, is not vendored); its pod templates are core/v1 pod templates
and are validated as such. The overlay is rendered by a small kustomize subset below (resources,
images, RFC 6902 patches), which refuses any kustomization key it does not implement, since no
kustomize binary is installed here. Then cross-references: selectors, ports, names, the Secret.
And against the server: every ESRP_* variable the image, compose file, manifests and
docs/challenge.md's excerpt set is one esrp-server reads (from its sources), each artifact's
environment parses (`esrp-server health-check` with it, where a built esrp-server is at hand), the
termination grace outlasts the server's drain, and the volumes it writes are writable by its user.
"""

from __future__ import annotations

import copy
import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import jsonpatch
import jsonschema
import kubernetes_validate
import pytest
import yaml

DOCKER = Path(__file__).resolve().parents[1]
ROOT = DOCKER.parent
K8S = DOCKER / "k8s"
# Native gRPC probes are GA from 1.27; 1.29 is the oldest we claim, 1.37 the newest schemas shipped.
KUBERNETES_VERSIONS = ("1.29.0", "1.37.0")

Resource = dict[str, Any]


def load_all(path: Path) -> list[Resource]:
    """The YAML documents of a file (empty ones dropped)."""
    with path.open() as f:
        return [d for d in yaml.safe_load_all(f) if d]


def kustomize_build(directory: Path) -> list[Resource]:
    """Renders a kustomization with the subset of kustomize that these manifests use."""
    kustomization = load_all(directory / "kustomization.yaml")[0]
    understood = {"apiVersion", "kind", "resources", "patches", "images"}
    unknown = set(kustomization) - understood
    assert not unknown, f"{directory}: this test's kustomize subset does not implement {sorted(unknown)}"
    assert kustomization["apiVersion"] == "kustomize.config.k8s.io/v1beta1"
    assert kustomization["kind"] == "Kustomization"
    resources: list[Resource] = []
    for entry in kustomization.get("resources", []):
        path = directory / entry
        resources += kustomize_build(path) if path.is_dir() else load_all(path)
    for patch in kustomization.get("patches", []):
        assert set(patch) == {"path", "target"}, f"{directory}: only path + target patches: {patch}"
        operations = load_all(directory / patch["path"])[0]
        assert isinstance(operations, list), f"{patch['path']}: a JSON 6902 patch (a list of operations)"
        target = patch["target"]
        matched = [r for r in resources if matches(r, target)]
        assert matched, f"{directory}: the patch target {target} matches nothing"
        for resource in matched:
            patched = jsonpatch.apply_patch(resource, operations)
            resource.clear()
            resource.update(patched)
    for image in kustomization.get("images", []):
        for container in containers(resources):
            name, _, _ = container["image"].partition(":")
            if name == image["name"]:
                container["image"] = f"{image.get('newName', name)}:{image.get('newTag', 'latest')}"
    return resources


def matches(resource: Resource, target: dict[str, str]) -> bool:
    """Whether a kustomize patch target selects the resource."""
    group, _, version = resource["apiVersion"].rpartition("/")
    wanted = {
        "group": group,
        "version": version,
        "kind": resource["kind"],
        "name": resource["metadata"]["name"],
    }
    return all(wanted[key] == value for key, value in target.items())


def pod_specs(resources: list[Resource]) -> list[Resource]:
    """Every pod spec in workloads and RayJobs."""
    specs = []
    for r in resources:
        if r["kind"] == "StatefulSet":
            specs.append(r["spec"]["template"]["spec"])
        if r["kind"] == "RayJob":
            specs += [t["spec"] for t in ray_templates(r)]
    return specs


def containers(resources: list[Resource]) -> list[Resource]:
    """Every container of every pod spec."""
    return [c for spec in pod_specs(resources) for c in spec["containers"]]


def ray_templates(rayjob: Resource) -> list[Resource]:
    """The pod templates of a RayJob's cluster: head, then each worker group."""
    cluster = rayjob["spec"]["rayClusterSpec"]
    return [cluster["headGroupSpec"]["template"]] + [
        g["template"] for g in cluster.get("workerGroupSpecs", [])
    ]


def validate(resource: Resource, version: str) -> None:
    """Strict validation against the Kubernetes schemas of `version`; the error names the object."""
    try:
        kubernetes_validate.validate(resource, version, strict=True)
    except kubernetes_validate.ValidationError as e:
        path = "/".join(str(p) for p in e.path)
        name = f"{resource['kind']}/{resource['metadata']['name']}"
        pytest.fail(f"{name} is invalid for Kubernetes {version} at {path}: {e.message}")


def env(container: Resource) -> dict[str, Any]:
    """A container's environment: name to value, or to valueFrom."""
    return {e["name"]: e.get("value", e.get("valueFrom")) for e in container.get("env", [])}


BASE = kustomize_build(K8S / "base")
GPU = kustomize_build(K8S / "gpu")
RAY = [r for path in sorted((K8S / "ray").glob("*.yaml")) for r in load_all(path)]
RAYJOB = next(r for r in RAY if r["kind"] == "RayJob")


def by_kind(resources: list[Resource], kind: str) -> Resource:
    """The one resource of a kind."""
    (found,) = [r for r in resources if r["kind"] == kind]
    return found


# --- Schemas ---


@pytest.mark.parametrize("version", KUBERNETES_VERSIONS)
@pytest.mark.parametrize("variant", ["base", "gpu", "ray"])
def test_every_kubernetes_object_is_valid(variant: str, version: str) -> None:
    resources = {"base": BASE, "gpu": GPU, "ray": RAY}[variant]
    for resource in resources:
        if resource["kind"] == "RayJob":
            # Its pod templates are core/v1 PodTemplateSpecs inside the custom resource.
            for i, template in enumerate(ray_templates(resource)):
                pod_template = {"apiVersion": "v1", "kind": "PodTemplate", "metadata": {"name": f"ray-{i}"}}
                validate({**pod_template, "template": template}, version)
        else:
            validate(resource, version)


def test_every_manifest_file_is_used() -> None:
    """A file in base/ or gpu/ that no kustomization lists would be silently left out."""
    for directory in (K8S / "base", K8S / "gpu"):
        kustomization = load_all(directory / "kustomization.yaml")[0]
        listed = set(kustomization.get("resources", [])) | {
            p["path"] for p in kustomization.get("patches", [])
        }
        files = {p.name for p in directory.glob("*.yaml")} - {"kustomization.yaml"}
        assert files <= listed, f"{directory}: not in kustomization.yaml: {sorted(files - listed)}"


def strict(properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    """An object schema that rejects unknown fields."""
    return {
        "type": "object",
        "properties": properties,
        "required": list(required),
        "additionalProperties": False,
    }


ANY = {}
INT32 = {"type": "integer", "minimum": -(2**31), "maximum": 2**31 - 1}
STRING_MAP = {"type": "object", "additionalProperties": {"type": "string"}}
TEMPLATE = {"type": "object"}  # validated as a core/v1 PodTemplateSpec above
# KubeRay v1.7.0, ray.io/v1 RayJob: every spec field name (unknown names are typos); types where
# this project's manifest sets them. submissionMode's values are KubeRay's JobSubmissionMode.
RAYJOB_SCHEMA = strict(
    {
        "apiVersion": {"const": "ray.io/v1"},
        "kind": {"const": "RayJob"},
        "metadata": {"type": "object", "required": ["name"]},
        "spec": strict(
            {
                "activeDeadlineSeconds": INT32,
                "backoffLimit": INT32,
                "clusterSelector": STRING_MAP,
                "deletionStrategy": ANY,
                "entrypoint": {"type": "string", "minLength": 1},
                "entrypointNumCpus": {"type": "number"},
                "entrypointNumGpus": {"type": "number"},
                "entrypointResources": {"type": "string"},
                "jobId": {"type": "string"},
                "managedBy": {"type": "string"},
                "metadata": STRING_MAP,
                "preRunningDeadlineSeconds": INT32,
                "rayClusterSpec": strict(
                    {
                        "authOptions": ANY,
                        "autoscalerOptions": ANY,
                        "enableInTreeAutoscaling": {"type": "boolean"},
                        "gcsFaultToleranceOptions": ANY,
                        "headGroupSpec": strict(
                            {
                                "enableIngress": {"type": "boolean"},
                                "headService": ANY,
                                "ingressOptions": ANY,
                                "labels": STRING_MAP,
                                "rayStartParams": STRING_MAP,
                                "resources": STRING_MAP,
                                "serviceType": {"type": "string"},
                                "template": TEMPLATE,
                            },
                            # KubeRay before v1.1 also required rayStartParams: kept for them.
                            required=("template", "rayStartParams"),
                        ),
                        "headServiceAnnotations": STRING_MAP,
                        "historyServerOptions": ANY,
                        "managedBy": {"type": "string"},
                        "networkPolicy": ANY,
                        "rayVersion": {"type": "string", "pattern": r"^\d+\.\d+\.\d+$"},
                        "suspend": {"type": "boolean"},
                        "tlsOptions": ANY,
                        "upgradeStrategy": ANY,
                        "workerGroupSpecs": {
                            "type": "array",
                            "items": strict(
                                {
                                    "groupName": {"type": "string", "minLength": 1},
                                    "idleTimeoutSeconds": INT32,
                                    "labels": STRING_MAP,
                                    "maxReplicas": INT32,
                                    "minReplicas": INT32,
                                    "numOfHosts": INT32,
                                    "priority": ANY,
                                    "rayStartParams": STRING_MAP,
                                    "replicas": INT32,
                                    "resources": STRING_MAP,
                                    "scaleStrategy": ANY,
                                    "suspend": {"type": "boolean"},
                                    "template": TEMPLATE,
                                },
                                required=(
                                    "groupName",
                                    "maxReplicas",
                                    "minReplicas",
                                    "rayStartParams",
                                    "template",
                                ),
                            ),
                        },
                    },
                    required=("headGroupSpec",),
                ),
                "runtimeEnvYAML": {"type": "string"},
                "shutdownAfterJobFinishes": {"type": "boolean"},
                "submissionMode": {"enum": ["K8sJobMode", "HTTPMode", "InteractiveMode", "SidecarMode"]},
                "submitterConfig": ANY,
                "submitterPodTemplate": TEMPLATE,
                "suspend": {"type": "boolean"},
                "ttlSecondsAfterFinished": INT32,
            },
            required=("entrypoint", "rayClusterSpec"),
        ),
    },
    required=("apiVersion", "kind", "metadata", "spec"),
)


def test_the_rayjob_matches_kuberay_s_rayjob_fields() -> None:
    jsonschema.validate(RAYJOB, RAYJOB_SCHEMA)
    # And the schema is not vacuous: a misspelt field fails.
    broken = copy.deepcopy(RAYJOB)
    broken["spec"]["rayClusterSpec"]["workerGroupSpecs"][0]["replica"] = 2
    with pytest.raises(jsonschema.ValidationError, match="replica"):
        jsonschema.validate(broken, RAYJOB_SCHEMA)


def test_strict_validation_rejects_an_unknown_field() -> None:
    """The schemas really are strict (a typo in a probe would otherwise pass)."""
    statefulset = copy.deepcopy(by_kind(BASE, "StatefulSet"))
    statefulset["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["grpcc"] = {"port": 1}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(statefulset, KUBERNETES_VERSIONS[0], strict=True)


# --- What the objects must say to one another ---


@pytest.mark.parametrize("variant", ["base", "gpu"])
def test_the_headless_service_selects_the_statefulset_s_pods(variant: str) -> None:
    resources = {"base": BASE, "gpu": GPU}[variant]
    service, statefulset = by_kind(resources, "Service"), by_kind(resources, "StatefulSet")
    assert service["spec"]["clusterIP"] == "None", "headless: DNS names every pod"
    assert statefulset["spec"]["serviceName"] == service["metadata"]["name"]
    labels = statefulset["spec"]["template"]["metadata"]["labels"]
    assert service["spec"]["selector"].items() <= labels.items()
    assert statefulset["spec"]["selector"]["matchLabels"].items() <= labels.items()
    container = statefulset["spec"]["template"]["spec"]["containers"][0]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    assert {p["targetPort"] for p in service["spec"]["ports"]} <= set(ports)


@pytest.mark.parametrize("variant", ["base", "gpu"])
def test_probes_metrics_and_token_agree_with_the_server_s_settings(variant: str) -> None:
    statefulset = by_kind({"base": BASE, "gpu": GPU}[variant], "StatefulSet")
    pod = statefulset["spec"]["template"]
    container = pod["spec"]["containers"][0]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    settings = env(container)
    assert settings["ESRP_LISTEN"] == f"0.0.0.0:{ports['grpc']}"
    assert settings["ESRP_METRICS_LISTEN"] == f"0.0.0.0:{ports['metrics']}"
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["grpc"]["port"] == ports["grpc"], probe
    annotations = pod["metadata"]["annotations"]
    assert annotations["prometheus.io/scrape"] == "true"
    assert annotations["prometheus.io/port"] == str(ports["metrics"])
    assert settings["ESRP_TOKEN"] == {"secretKeyRef": {"name": "esrp-token", "key": "token"}}
    resources = container["resources"]
    assert {"cpu", "memory"} <= set(resources["requests"])
    assert {"cpu", "memory"} <= set(resources["limits"])
    # The image's user, and a read-only root with a writable /tmp.
    assert pod["spec"]["securityContext"]["runAsUser"] == 10001
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    assert {"name": "tmp", "mountPath": "/tmp"} in container["volumeMounts"]


def test_the_gpu_overlay_asks_for_one_gpu_and_changes_nothing_else_of_the_server() -> None:
    base, gpu = by_kind(BASE, "StatefulSet"), by_kind(GPU, "StatefulSet")
    container = gpu["spec"]["template"]["spec"]["containers"][0]
    assert container["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert "nvidia.com/gpu" not in base["spec"]["template"]["spec"]["containers"][0]["resources"]["limits"]
    toleration = {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"}
    assert toleration in gpu["spec"]["template"]["spec"]["tolerations"]
    base_container = copy.deepcopy(base["spec"]["template"]["spec"]["containers"][0])
    gpu_container = copy.deepcopy(container)
    del base_container["resources"], gpu_container["resources"]
    assert base_container == gpu_container
    assert by_kind(BASE, "Service") == by_kind(GPU, "Service")


def test_the_rayjob_lists_every_server_pod_by_its_stable_name() -> None:
    service, statefulset = by_kind(BASE, "Service"), by_kind(BASE, "StatefulSet")
    head = RAYJOB["spec"]["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]["containers"][0]
    port = next(p["port"] for p in service["spec"]["ports"] if p["name"] == "grpc")
    name, service_name = statefulset["metadata"]["name"], service["metadata"]["name"]
    expected = [f"{name}-{i}.{service_name}:{port}" for i in range(statefulset["spec"]["replicas"])]
    assert env(head)["ESRP_SERVERS"].split(",") == expected
    for container in containers([RAYJOB]):
        assert env(container)["ESRP_TOKEN"] == {"secretKeyRef": {"name": "esrp-token", "key": "token"}}
    claims = [v["persistentVolumeClaim"]["claimName"] for v in ray_templates(RAYJOB)[0]["spec"]["volumes"]]
    assert claims == [by_kind(RAY, "PersistentVolumeClaim")["metadata"]["name"]]
    assert "--ray" in RAYJOB["spec"]["entrypoint"]


# --- Compose ---


def compose_command() -> list[str] | None:
    """`docker compose` (the plugin) or `docker-compose` (v1), whichever is here."""
    docker = shutil.which("docker")
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0:
        return [docker, "compose"]
    if legacy := shutil.which("docker-compose"):
        return [legacy]
    return None


def test_the_compose_file_is_valid_and_its_replicas_have_ports_of_their_own() -> None:
    compose = compose_command()
    if compose is None:
        pytest.skip("neither `docker compose` nor `docker-compose` is here (apt-get install docker-compose)")
    result = subprocess.run(
        [*compose, "-p", "esrp", "-f", str(DOCKER / "compose.yaml"), "config"],
        capture_output=True,
        text=True,
        env={"PATH": "/usr/local/bin:/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr
    config = yaml.safe_load(result.stdout)
    services = config["services"]
    servers = {name: s for name, s in services.items() if name.startswith("server-")}
    assert len(servers) >= 2
    # `config` writes every environment as a mapping.
    listen_ports = [s["environment"]["ESRP_LISTEN"].rsplit(":", 1)[1] for s in servers.values()]
    metrics_ports = [s["environment"]["ESRP_METRICS_LISTEN"].rsplit(":", 1)[1] for s in servers.values()]
    assert len(set(listen_ports + metrics_ports)) == 2 * len(servers), "every replica on ports of its own"
    assert all(s["network_mode"] == "host" for s in services.values())
    job = services["eval"]
    assert set(job["depends_on"]) == set(servers)
    assert all(c["condition"] == "service_healthy" for c in job["depends_on"].values())
    job_env = job["environment"]
    assert [job_env[f"ESRP_SERVER_{i}"] for i in range(len(servers))] == [
        f"http://127.0.0.1:{p}" for p in listen_ports
    ]


# --- What the artifacts tell the server, against what it reads ---

SERVER_SOURCES = [ROOT / "server/service/src" / name for name in ("config.rs", "health_check.rs")]
# The variables esrp-server reads: one per flag (`env = "ESRP_..."`), and ESRP_LOG (the log level).
SERVER_VARIABLES = {
    name for path in SERVER_SOURCES for name in re.findall(r'env = "(ESRP_[A-Z0-9_]+)"', path.read_text())
} | {"ESRP_LOG"}
# The image's user, which owns nothing on a fresh volume.
IMAGE_USER = 10001


def dockerfile_env(path: Path) -> dict[str, str]:
    """The variables a Dockerfile's ENV instructions set (`ENV A=1 \\ B=2` form)."""
    text = re.sub(r"\\\n\s*", " ", path.read_text())
    found: dict[str, str] = {}
    for line in text.splitlines():
        if line.startswith("ENV "):
            found.update(pair.split("=", 1) for pair in line[4:].split())
    return found


def challenge_excerpt() -> dict[str, Any]:
    """The pod spec excerpt of docs/challenge.md's "Containers and Kubernetes"."""
    text = (ROOT / "docs/challenge.md").read_text()
    section = text[text.index("### Containers and Kubernetes") :]
    block = re.search(r"```yaml\n(.*?)```", section, re.DOTALL)
    assert block, "docs/challenge.md: no yaml excerpt under Containers and Kubernetes"
    excerpt: dict[str, Any] = yaml.safe_load(block.group(1))
    return excerpt


def challenge_statefulset() -> Resource:
    """The base StatefulSet as docs/challenge.md tells an organiser to change it."""
    statefulset = copy.deepcopy(by_kind(BASE, "StatefulSet"))
    statefulset["spec"]["replicas"] = 1
    spec, excerpt = statefulset["spec"]["template"]["spec"], challenge_excerpt()
    spec["securityContext"].update(excerpt["securityContext"])
    (server,) = spec["containers"]
    (changes,) = excerpt["containers"]
    assert changes["name"] == server["name"]
    server["env"] = [e for e in server["env"] if e["name"] != "ESRP_TOKEN"] + changes["env"]
    server["volumeMounts"] += changes["volumeMounts"]
    spec["volumes"] += excerpt["volumes"]
    return statefulset


def test_every_server_variable_the_artifacts_set_is_one_the_server_reads() -> None:
    assert {"ESRP_LISTEN", "ESRP_TOKEN", "ESRP_SHUTDOWN_GRACE_MS"} <= SERVER_VARIABLES  # the parse works
    image = {n for n in dockerfile_env(DOCKER / "server.Dockerfile") if n.startswith("ESRP_")}
    assert image == {"ESRP_LISTEN", "ESRP_SCENE_CACHE"}
    compose = load_all(DOCKER / "compose.yaml")[0]
    compose_servers = {
        entry.split("=", 1)[0]
        for name, service in compose["services"].items()
        if name.startswith("server-")
        for entry in service["environment"]
    }
    manifests = {name for r in BASE + GPU for c in containers([r]) for name in env(c)}
    challenge = set(env(challenge_excerpt()["containers"][0]))
    for where, names in [
        ("server.Dockerfile", image),
        ("compose.yaml", compose_servers),
        ("k8s", manifests),
        ("docs/challenge.md", challenge),
    ]:
        unknown = names - SERVER_VARIABLES
        assert not unknown, f"{where} sets variables esrp-server does not read: {sorted(unknown)}"


def server_binary() -> Path | None:
    """The esrp-server to ask: ESRP_SERVER_BIN (scripts/docker-tests.sh), else a debug build here."""
    for candidate in (os.environ.get("ESRP_SERVER_BIN"), ROOT / "target/debug/esrp-server"):
        if candidate and Path(candidate).is_file():
            return Path(candidate)
    return None


def resolved(settings: dict[str, Any]) -> dict[str, str]:
    """A container's environment with a stand-in for each value from a Secret."""
    return {
        name: value if isinstance(value, str) else "0123456789abcdef-secret"
        for name, value in settings.items()
    }


@pytest.mark.parametrize("variant", ["image", "base", "gpu", "challenge"])
def test_the_server_accepts_the_environment_each_artifact_gives_it(variant: str) -> None:
    """Its flags parse from these variables: `health-check` reads them as the server does, and
    then fails only to connect (1), not on a refused value (clap's 2)."""
    binary = server_binary()
    if binary is None:
        pytest.skip("no esrp-server built (cargo build -p esrp-server, or ESRP_SERVER_BIN)")
    image = dockerfile_env(DOCKER / "server.Dockerfile")
    container = {
        "image": {},
        "base": env(containers(BASE)[0]),
        "gpu": env(containers(GPU)[0]),
        "challenge": env(containers([challenge_statefulset()])[0]),
    }[variant]
    environment = {"PATH": "/usr/bin:/bin", **image, **resolved(container)}
    result = subprocess.run(
        [str(binary), "health-check", "127.0.0.1:1", "--timeout-ms", "2000"],
        capture_output=True,
        text=True,
        env=environment,
        timeout=60,
    )
    assert result.returncode == 1, result.stderr
    assert "cannot connect" in result.stderr, result.stderr


@pytest.mark.parametrize("variant", ["base", "gpu"])
def test_the_termination_grace_outlasts_the_server_s_drain(variant: str) -> None:
    pod = by_kind({"base": BASE, "gpu": GPU}[variant], "StatefulSet")["spec"]["template"]["spec"]
    config = (ROOT / "server/service/src/config.rs").read_text()
    default = re.search(r'env = "ESRP_SHUTDOWN_GRACE_MS", default_value_t = ([0-9_]+)', config)
    assert default, "config.rs: ESRP_SHUTDOWN_GRACE_MS's default not found"
    grace_ms = int(env(pod["containers"][0]).get("ESRP_SHUTDOWN_GRACE_MS", default.group(1).replace("_", "")))
    # The drain, then closing the episodes (their records written) and stopping the renderer.
    assert pod["terminationGracePeriodSeconds"] * 1000 >= grace_ms + 10_000


def test_the_challenge_excerpt_fits_the_statefulset() -> None:
    """docs/challenge.md's changes to the StatefulSet give a valid pod that can write its records."""
    statefulset = challenge_statefulset()
    for version in KUBERNETES_VERSIONS:
        validate(statefulset, version)
    spec = statefulset["spec"]["template"]["spec"]
    settings = env(spec["containers"][0])
    assert "ESRP_TOKENS" in settings
    assert "ESRP_TOKEN" not in settings, "the server refuses ESRP_TOKEN with ESRP_TOKENS"
    assert spec["securityContext"]["runAsUser"] == IMAGE_USER
    assert spec["securityContext"]["fsGroup"] == IMAGE_USER, "the records volume must be writable"
    mounts = {m["mountPath"]: m["name"] for m in spec["containers"][0]["volumeMounts"]}
    claims = {v["name"] for v in spec["volumes"] if "persistentVolumeClaim" in v}
    assert mounts[settings["ESRP_RECORDS"]] in claims, "the records on a persistent volume"
    assert settings["ESRP_TOKENS"].startswith(next(p for p, n in mounts.items() if n == "tokens") + "/")


def test_the_ray_head_can_write_its_results_volume() -> None:
    assert f"USER {IMAGE_USER}:{IMAGE_USER}" in (DOCKER / "eval.Dockerfile").read_text()
    head = ray_templates(RAYJOB)[0]["spec"]
    assert head["securityContext"]["fsGroup"] == IMAGE_USER
