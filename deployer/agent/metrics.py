"""``GET /metrics``: the agent's state in the Prometheus text format, through the official client library.

A collector reads the agent's state at scrape time (nothing is counted twice, and nothing costs anything
between scrapes); counters come from the database at start, so they survive restarts.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

if TYPE_CHECKING:
    from .core import Agent

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class AgentCollector(Collector):
    def __init__(self, agent: Agent) -> None:
        self.agent = agent

    def collect(self) -> Iterator[Metric]:
        from .model import STATUSES
        from .views import windows_json

        a = self.agent
        status = GaugeMetricFamily(
            "deployer_device_status", "1 for the device's current status, 0 for the others", labels=["device", "status"]
        )
        drifted = GaugeMetricFamily(
            "deployer_device_drifted", "1 while the device does not hold the adopted state", labels=["device"]
        )
        drift_events = CounterMetricFamily(
            "deployer_drift_events", "drift found (each time it starts)", labels=["device"]
        )
        restores = CounterMetricFamily(
            "deployer_drift_restores", "restores of the adopted state that verified", labels=["device"]
        )
        replaced = CounterMetricFamily(
            "deployer_device_replaced", "times the device was found replaced", labels=["device"]
        )
        writes = CounterMetricFamily(
            "deployer_register_writes", "write and commit requests sent (the ledger)", labels=["device"]
        )
        last = GaugeMetricFamily(
            "deployer_last_check_timestamp_seconds", "when the device was last read", labels=["device"]
        )
        pending = GaugeMetricFamily(
            "deployer_device_pending_changes", "parameters whose files' value is not adopted yet", labels=["device"]
        )
        owned = GaugeMetricFamily(
            "deployer_device_owned", "1 when the agent holds the device's lock", labels=["device"]
        )
        for d in a.devices.values():
            current = "running" if d.run else d.status
            for s in STATUSES:
                status.add_metric([d.name, s], 1.0 if s == current else 0.0)
            drifted.add_metric([d.name], 1.0 if d.drift else 0.0)
            drift_events.add_metric([d.name], d.drift_events)
            restores.add_metric([d.name], d.drift_restores)
            replaced.add_metric([d.name], d.replaced_total)
            writes.add_metric([d.name], d.writes)
            if d.last_check is not None:
                last.add_metric([d.name], d.last_check)
            pending.add_metric([d.name], len(d.pending))
            owned.add_metric([d.name], 1.0 if d.owned else 0.0)
        yield from (status, drifted, drift_events, restores, replaced, writes, last, pending, owned)
        windows = GaugeMetricFamily("deployer_pending_windows", "open soak and confirm windows", labels=["kind"])
        open_windows = windows_json(a) if a.store is not None else []
        for kind in ("soak", "confirm"):
            windows.add_metric([kind], sum(1 for w in open_windows if w["kind"] == kind))
        yield windows
        runs = GaugeMetricFamily("deployer_runs_in_flight", "runs the agent executes now")
        runs.add_metric([], sum(1 for r in a.runs.live.values() if r.state in ("running", "waiting")))
        yield runs
        checks = CounterMetricFamily("deployer_checks", "rounds of the watch completed")
        checks.add_metric([], a.watch.checks)
        yield checks
        took = GaugeMetricFamily("deployer_check_duration_seconds", "how long the last round of the watch took")
        took.add_metric([], a.watch.check_seconds)
        yield took


def registry(agent: Agent) -> CollectorRegistry:
    reg = CollectorRegistry(auto_describe=False)
    reg.register(AgentCollector(agent))
    return reg


def exposition(reg: CollectorRegistry) -> bytes:
    return generate_latest(reg)
