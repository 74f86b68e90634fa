"""The deployment files hold the service's own bounds (docs/deployment.md): every container
running quietframe has a memory limit at least its base + history budget + memory budget + the
overhead above them, with the budgets its environment sets (or the defaults); the autoscaler
scales the replicas on a metric the service exports; HAProxy has a server slot for every
replica the autoscaler may run. Reads deploy/k8s/*.yaml and deploy/docker-compose.yml."""

from __future__ import annotations

import os
import re
from pathlib import Path
from types import SimpleNamespace

import pytest

yaml = pytest.importorskip("yaml")

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
# `quietframe serve` after start-up (all 13 installed models loaded and warmed up): 354-361 MiB
# RSS measured with 2 and 8 threads; 1 GiB leaves room for another image's libraries.
BASE_MIB = 1024
# Allocator and connections beyond the budgets: 40 MiB measured, 96 MiB stated
# (docs/reliability.md); rounded up.
SLACK_MIB = 512
UNITS_MIB = {"": 2**-20, "k": 2**-10, "m": 1, "g": 2**10, "t": 2**20,
             "ki": 2**-10, "mi": 1, "gi": 2**10, "ti": 2**20}


def mib(quantity: str | int) -> float:
    """A Kubernetes quantity (24Gi, 512Mi) or a Compose size (12g, 512m) in MiB. Both read a
    bare K/M/G as powers of 1024 here: Compose does; for Kubernetes (powers of 1000) it is the
    smaller reading, so a limit it passes holds either way."""
    match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([a-zA-Z]*?)b?", str(quantity).strip())
    assert match, f"not a memory size: {quantity!r}"
    number, unit = match.groups()
    return float(number) * UNITS_MIB[unit.lower()]


def k8s_documents() -> list[dict]:
    docs = []
    for path in sorted((DEPLOY / "k8s").glob("*.yaml")):
        docs += [d for d in yaml.safe_load_all(path.read_text()) if d]
    return docs


def of_kind(kind: str) -> list[dict]:
    return [d for d in k8s_documents() if d["kind"] == kind]


def runs_quietframe(image: str | None) -> bool:
    return (image or "").split("/")[-1].startswith("quietframe")


def k8s_containers() -> list[tuple[str, dict[str, str], str | None]]:
    """(name, environment, memory limit) of every container running quietframe."""
    found = []
    for doc in k8s_documents():
        template = doc.get("spec", {}).get("template")
        for container in (template or {}).get("spec", {}).get("containers", []):
            if runs_quietframe(container.get("image")):
                env = {e["name"]: str(e["value"]) for e in container.get("env", [])
                       if "value" in e}
                limit = container.get("resources", {}).get("limits", {}).get("memory")
                found.append((f"k8s {doc['metadata']['name']}/{container['name']}", env, limit))
    return found


def compose_containers() -> list[tuple[str, dict[str, str], str | None]]:
    compose = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    found = []
    for name, service in compose["services"].items():
        if runs_quietframe(service.get("image")):
            limit = service.get("mem_limit") or (
                service.get("deploy", {}).get("resources", {}).get("limits", {}).get("memory"))
            env = {k: str(v) for k, v in (service.get("environment") or {}).items()}
            found.append((f"compose {name}", env, limit))
    return found


def settings_in(env: dict[str, str], monkeypatch):
    """The Settings a container computes: its environment over the defaults (the test's own
    QUIETFRAME_* variables left out)."""
    from quietframe.service.settings import Settings

    for name in list(os.environ):
        if name.startswith("QUIETFRAME_"):
            monkeypatch.delenv(name)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    return Settings()


def bound_mib(env: dict[str, str], monkeypatch) -> float:
    """base + history budget + memory budget + overhead: the slack, and the arena an idle model
    keeps of its largest tile (a tile holds at most QUIETFRAME_MAX_MEMORY_MB)."""
    from quietframe.runtime.settings import RuntimeSettings

    settings = settings_in(env, monkeypatch)
    # the container's QUIETFRAME_MAX_MEMORY_MB, set just above (read afresh: not the cached one)
    arena = RuntimeSettings.from_environ().max_memory_mb
    return BASE_MIB + settings.history_budget_mb + settings.memory_budget_mb + SLACK_MIB + arena


CONTAINERS = k8s_containers() + compose_containers()


def test_the_files_run_quietframe_in_k8s_and_compose():
    names = [name for name, _, _ in CONTAINERS]
    assert any(n.startswith("k8s") for n in names) and sum(
        n.startswith("compose") for n in names) >= 2, names


@pytest.mark.parametrize(("name", "env", "limit"), CONTAINERS, ids=[c[0] for c in CONTAINERS])
def test_the_memory_limit_holds_the_services_own_bound(name, env, limit, monkeypatch):
    """Below the bound a busy container is OOM-killed before the service's limits (429/413,
    the history budget) act."""
    assert limit is not None, f"{name}: no memory limit"
    need = bound_mib(env, monkeypatch)
    assert mib(limit) >= need, (
        f"{name}: memory limit {limit} = {mib(limit):.0f} MiB < {need:.0f} MiB (base {BASE_MIB} "
        f"+ history + memory budgets + overhead)")


def test_k8s_requests_the_memory_it_may_use():
    """request = limit: scheduled where the whole bound fits, never evicted for using it."""
    for doc in of_kind("StatefulSet"):
        for container in doc["spec"]["template"]["spec"]["containers"]:
            if runs_quietframe(container["image"]):
                resources = container["resources"]
                assert mib(resources["requests"]["memory"]) == mib(resources["limits"]["memory"])


def haproxy_servers(backend: str) -> list[str]:
    """Server names of one backend of the k8s ConfigMap's haproxy.cfg, in order."""
    config = next(d for d in of_kind("ConfigMap") if "haproxy.cfg" in d["data"])
    servers, current = [], None
    for line in config["data"]["haproxy.cfg"].splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] in ("backend", "frontend", "defaults", "global", "resolvers", "listen"):
            current = words[1] if len(words) > 1 else None
        elif current == backend and words[0] == "server":
            servers.append(words[1])
        elif current == backend and words[0] == "server-template":
            pytest.fail("a server-template fills its slots in DNS order (see haproxy.yaml)")
    return servers


def autoscaler() -> dict:
    (hpa,) = of_kind("HorizontalPodAutoscaler")
    assert hpa["apiVersion"] == "autoscaling/v2"
    return hpa


def test_haproxy_has_a_slot_for_every_replica_the_autoscaler_may_run():
    hpa = autoscaler()
    (statefulset,) = [d for d in of_kind("StatefulSet")
                      if d["metadata"]["name"] == hpa["spec"]["scaleTargetRef"]["name"]]
    name = statefulset["metadata"]["name"]
    slots = haproxy_servers("by_session")
    assert len(slots) >= hpa["spec"]["maxReplicas"], (len(slots), hpa["spec"]["maxReplicas"])
    # the StatefulSet's pod names, in ordinal order: every HAProxy pod builds the same ring
    assert slots == [f"{name}-{i}" for i in range(len(slots))]
    assert haproxy_servers("create") == slots


def test_the_autoscaler_scales_the_replicas_on_a_metric_the_service_exports():
    from quietframe.service.metrics import Metrics

    hpa = autoscaler()["spec"]
    assert hpa["scaleTargetRef"]["kind"] == "StatefulSet"
    assert 1 <= hpa["minReplicas"] <= hpa["maxReplicas"]
    (metric,) = hpa["metrics"]
    served = metric["pods"]["metric"]["name"]
    adapter = next(d for d in of_kind("ConfigMap") if "config.yaml" in d["data"])
    rules = yaml.safe_load(adapter["data"]["config.yaml"])["rules"]
    (rule,) = [r for r in rules if r["name"]["as"] == served]
    exported = set(re.findall(r"^(quietframe_\w+)", Metrics().render().decode(), re.M))
    queried = set(re.findall(r"quietframe_\w+", rule["seriesQuery"] + rule["metricsQuery"]))
    assert queried and queried <= exported, queried - exported


def test_the_load_gauges_count_uploads_and_frames_holding_their_session():
    from quietframe.service.metrics import Metrics
    from quietframe.service.routers.health import observe_load

    def session(busy: bool) -> SimpleNamespace:
        return SimpleNamespace(lock=SimpleNamespace(locked=lambda: busy))

    registry = SimpleNamespace(
        sessions={"a": session(True), "b": session(False), "c": session(True)},
        upload_slots=SimpleNamespace(count=2),
        admission=SimpleNamespace(used_bytes=3 << 20),
        settings=SimpleNamespace(worker_count=4),
    )
    metrics = Metrics()
    observe_load(metrics, registry)  # type: ignore[arg-type]
    text = metrics.render().decode()
    assert "quietframe_frames_in_flight 4.0" in text  # 2 uploads + 2 sessions denoising
    assert "quietframe_frame_slots 4.0" in text
    assert "quietframe_memory_reserved_bytes 3.145728e+06" in text
