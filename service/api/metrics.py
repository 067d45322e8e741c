"""`/metrics` in the Prometheus text format (prometheus-client), read from the job table and
the backend at scrape time: jobs by state, queue wait and run time histograms, workers."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from service.jobs.backend import Backend
from service.jobs.store import JobStore

#: histogram bucket bounds (s): from a block cutting to a day-long simulation
BUCKETS = (0.1, 0.5, 1.0, 5.0, 15.0, 60.0, 300.0, 1800.0, 3600.0, 6 * 3600.0, 86400.0)


def _histogram(name: str, doc: str, values: list[float]) -> HistogramMetricFamily:
    counts = [sum(v <= b for v in values) for b in BUCKETS]
    buckets: list[tuple[str, float]] = [(repr(b), float(c)) for b, c in zip(BUCKETS, counts,
                                                                          strict=True)]
    buckets.append(("+Inf", float(len(values))))
    return HistogramMetricFamily(name, doc, buckets=buckets, sum_value=float(sum(values)))


class JobCollector(Collector):
    """Collects the job and worker metrics of one service instance."""

    def __init__(self, store: JobStore, backend: Backend) -> None:
        self.store, self.backend = store, backend

    def collect(self) -> Iterator[Metric]:
        jobs = GaugeMetricFamily("polydda_jobs", "jobs in the job table by state",
                                 labels=["state"])
        for state, n in self.store.counts().items():
            jobs.add_metric([state], n)
        yield jobs
        yield _histogram("polydda_job_queue_wait_seconds",
                         "time from submission to start of the jobs that started",
                         self.store.durations("queue_wait"))
        yield _histogram("polydda_job_run_seconds", "run time of the jobs that ended",
                         self.store.durations("run_time"))
        health: dict[str, Any] = self.backend.health()
        workers = GaugeMetricFamily("polydda_workers", "workers that can run jobs now "
                                    "(embedded: job slots; rq: live polydda workers)")
        workers.add_metric([], float(health.get("workers", 0) or 0))
        yield workers
        busy = GaugeMetricFamily("polydda_workers_busy", "workers running a job")
        busy.add_metric([], float(health.get("busy", 0) or 0))
        yield busy


def make_registry(store: JobStore, backend: Backend) -> CollectorRegistry:
    """A registry of its own with the job metrics (the app's also has its requests')."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(JobCollector(store, backend))
    return registry
