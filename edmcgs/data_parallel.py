"""One training run over several workers on Ray Train (``edmcgs train REC -o CKPT --ray --workers N``).

The anchor windows share the motion networks, so a recording's windows are not independent jobs: the
run is data-parallel. Ray Train's ``TorchTrainer`` starts ``workers`` processes (``threads`` CPUs each)
joined in one torch.distributed group (gloo: CPUs); each opens the recording itself (its events left in
the file), builds the same model, and trains on its shard of the windows while ``model.train.sync``
averages the gradients every step. Rank 0 evaluates and writes the one checkpoint, as a single-process
run does (on a cluster, give paths on storage every node mounts).

Joins the cluster at ``RAY_ADDRESS`` when set (``--ray-address``), else starts a local Ray.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field

from edmcgs.errors import EdmcgsError, InvalidInputError, TrainingError
from edmcgs.fanout import check_cpus, ray_session
from edmcgs.options import RecordingOptions


@dataclass
class Job:
    """What every worker of a data-parallel run needs: the same recording, config and output (paths
    absolute: a worker runs in another directory, on a cluster on another machine)."""

    recording: str
    output: str
    config: str = "demo"
    overrides: list[str] = field(default_factory=list)
    options: RecordingOptions = field(default_factory=RecordingOptions)
    threads: int = 1
    """torch threads (and Ray CPUs) of each worker."""
    quiet: bool = False
    history: str | None = None
    """Rank 0 writes the periodic evaluation here (CSV), as ``--history`` does."""


def _worker(config: dict) -> None:
    """One worker's run (inside Ray Train: the process group is set up)."""
    import torch

    from edmcgs.model.train.sync import GradientSync
    from edmcgs.model.train.trainer import Trainer, write_history_csv
    from edmcgs.pipeline import build_config, new_model, open_recording, training_data

    job: Job = config["job"]
    torch.set_num_threads(job.threads)
    sync = GradientSync()
    rec = open_recording(job.recording, job.options, lazy_events=True)
    data = training_data(rec)
    model = new_model(data, build_config(job.config, job.overrides, rec))
    trainer = Trainer(model, data, progress=not job.quiet, sync=sync)
    history = trainer.fit(job.output if trainer.lead else None)
    if trainer.lead and job.history:
        write_history_csv(history, job.history)
    if trainer.lead:  # the split a cluster's speed-up is estimated from (bench.scale reads this line)
        steps = max(trainer.step // sync.world, 1)
        print(f"data-parallel: {sync.world} workers, {steps} steps each, {trainer.train_seconds:.1f} s "
              f"training, {sync.seconds:.1f} s of it exchanging gradients "
              f"({sync.bytes / steps / 1e6:.3f} MB per step)", flush=True)


def train(job: Job, workers: int, *, num_cpus: int | None = None) -> None:
    """Run ``job`` on ``workers`` Ray Train workers; rank 0 writes ``job.output``. A worker's
    EdmcgsError is raised as it is, any other failure as a TrainingError naming it."""
    if workers < 1 or job.threads < 1:
        raise InvalidInputError(f"--workers and --threads must be >= 1, got {workers} and {job.threads}")
    with ray_session(num_cpus) as ray:
        check_cpus(ray, workers * job.threads, f"{workers} workers of {job.threads} thread(s)")
        from ray.train import RunConfig, ScalingConfig, TrainingFailedError
        from ray.train.torch import TorchConfig, TorchTrainer

        storage = tempfile.mkdtemp(prefix="edmcgs-ray-train-")  # Ray Train's records (the checkpoint: ours)
        trainer = TorchTrainer(
            _worker, train_loop_config={"job": job}, torch_config=TorchConfig(backend="gloo"),
            scaling_config=ScalingConfig(num_workers=workers, use_gpu=False,
                                         resources_per_worker={"CPU": job.threads}),
            run_config=RunConfig(name="edmcgs-train", storage_path=storage))
        try:
            trainer.fit()
        except TrainingFailedError as exc:
            causes = [_cause(e) for e in (getattr(exc, "worker_failures", None) or {}).values()] or [exc]
            for cause in causes:
                if isinstance(cause, EdmcgsError):
                    raise cause from None
            lines = str(causes[0]).strip().splitlines() or [repr(causes[0])]
            raise TrainingError(f"data-parallel training failed: {lines[-1]}") from None
        finally:
            shutil.rmtree(storage, ignore_errors=True)


def _cause(exc: BaseException) -> BaseException:
    """The error a worker raised, out of what Ray wrapped it in."""
    seen = exc
    while seen is not None:
        if isinstance(seen, EdmcgsError):
            return seen
        seen = getattr(seen, "cause", None) or seen.__cause__
    return exc
