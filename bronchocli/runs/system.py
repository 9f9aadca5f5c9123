"""System metrics per run: MLflow's own sampler (CPU, memory, disk, network; GPUs through nvidia-ml-py).

``runs.system_metrics`` switches it, ``runs.system_metrics_interval_s`` sets
the sampling interval. MLflow's ``SystemMetricsMonitor`` samples in a thread
and logs ``system/*`` metrics (step = sample number) under the run's "System
metrics" tab; its GPU monitor needs NVIDIA's management library (the ``gpu``
extra, ``nvidia-ml-py``) and is skipped where that library or a GPU is
missing. MLflow drops the samples taken since its last log when it stops; the
stop here logs them, so a run shorter than one interval still has its sample.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

from ..config import Config

log = logging.getLogger(__name__)


def _start(cfg: Config, run_id: str, resume: bool):
    from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor  # lazy: psutil, only when on

    monitor = SystemMetricsMonitor(run_id, sampling_interval=cfg.runs.system_metrics_interval_s,
                                   resume_logging=resume, tracking_uri=cfg.paths.mlflow_uri)
    monitor.start()
    return monitor


def _stop(monitor) -> None:
    monitor.finish()
    rest = {k: v for k, v in monitor.aggregate_metrics().items() if v == v}  # samples not yet logged
    if rest:
        monitor.publish_metrics(rest)
        monitor.mlflow_logger.flush()


@contextmanager
def system_metrics(cfg: Config, run_id: str, resume: bool = False) -> Iterator[None]:
    """Sample the machine while the block runs (nothing when ``runs.system_metrics`` is off)."""
    monitor = None
    if cfg.runs.system_metrics:
        try:
            monitor = _start(cfg, run_id, resume)
        except Exception as exc:  # noqa: BLE001 - a missing psutil or sampler must not fail the run
            log.warning("system metrics off for run %s: %s", run_id, str(exc).splitlines()[0] if str(exc) else exc)
    try:
        yield
    finally:
        if monitor is not None:
            try:
                _stop(monitor)
            except Exception as exc:  # noqa: BLE001 - the run's result matters more than its last sample
                log.warning("system metrics of run %s: last sample not logged (%s)", run_id,  # one line, no SQL
                            (str(getattr(exc, "orig", None) or exc).strip().splitlines() or [type(exc).__name__])[0])
