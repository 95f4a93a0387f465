"""Run one experiment: set up Fabric, launch the processes, loop over rounds, track it.

``run_experiment(config)`` returns an :class:`ExperimentResult` in the process that
called it (rank 0). Multi-process runs use Fabric's launchers: ``runtime.launcher=ddp``
re-runs the current command once per extra process (what ``fedlgr run`` uses; several
nodes via ``fabric run`` / torchrun, which start the processes themselves), ``ddp_spawn``
spawns them from Python.
"""

from __future__ import annotations

import functools
import itertools
import time
from dataclasses import dataclass, field

from fedlgr.config import ExperimentConfig
from fedlgr.console import Progress, table
from fedlgr.federated.orchestrator import Orchestrator, RoundLog, torch_threads


@dataclass
class ExperimentResult:
    config: ExperimentConfig
    rounds: list[RoundLog] = field(default_factory=list)
    run_id: str | None = None
    seconds: float = 0.0
    after_tasks: list[dict[str, float]] = field(default_factory=list)  # FCL: per finished task

    @property
    def final(self) -> RoundLog:
        return self.rounds[-1]

    def rows(self) -> list[dict[str, object]]:
        return [row for r in self.rounds for row in r.rows()]

    def final_metrics(self) -> dict[str, float]:
        """Everything the run logged, as it stood at the end: the last round's metrics, the
        after-task summaries and the run-level costs (what a sweep's objective reads)."""
        out = dict(self.final.metrics()) if self.rounds else {}
        for after in self.after_tasks:
            out.update(after)
        out.update(self.cost_means())
        return out

    def cost_means(self) -> dict[str, float]:
        """Per client per round, averaged over clients and rounds (Tables III/IV):
        ``mean/cost/cpu_s``, ``mean/cost/wall_s``, ``mean/cost/bytes_up``, ... (GPU ones
        only where measured)."""
        import numpy as np

        out = {}
        for name, key in (
            ("cpu_s", "cpu_s"),
            ("wall_s", "wall_s"),
            ("gpu_util", "gpu_util"),
            ("gpu_mem_mb", "gpu_mem_mb"),
            ("bytes_up", "bytes_up"),
            ("bytes_down", "bytes_down"),
        ):
            column = np.concatenate([r.column(name) for r in self.rounds]) if self.rounds else []
            if len(column) and not np.isnan(column).all():
                out[f"mean/cost/{key}"] = float(np.nanmean(column))
        return out

    def summary(self) -> str:
        """Final per-client scores; costs averaged over all rounds (as Table III reports them);
        FCL: the scores after each task and the forgetting too."""
        import numpy as np

        last = self.final
        scores = ["test_loss", "test_rmse", "test_pcc"]
        costs = ["cpu_s", "wall_s", "bytes_up"]
        per_round = {n: np.mean([r.column(n) for r in self.rounds], axis=0) for n in costs}
        rows = [
            [
                f"client {c}",
                *(float(last.column(n)[c]) for n in scores),
                *(float(per_round[n][c]) for n in costs),
            ]
            for c in range(len(last.table))
        ]
        rows.append(
            ["mean", *(last.mean(n) for n in scores), *(float(per_round[n].mean()) for n in costs)]
        )
        for row in rows:
            row[-1] = _human_bytes(row[-1])
        headers = ["client", "loss", "RMSE", "PCC", "CPU s/round", "wall s/round", "upload/round"]
        text = table(headers, rows)
        if self.after_tasks:
            text += "\n\n" + self.task_summary()
        fidelity = self.replay_fidelity()
        if fidelity:
            text += "\n\n" + fidelity
        return text

    def replay_fidelity(self) -> str:
        """FedLGR: the replay's fidelity at each task end, mean over clients (README)."""
        names = {"fd_latent": "FD latents", "recon_mse": "recon MSE (held-out)"}
        names |= {"fd_labels": "FD labeller outputs", "vae_epochs": "VAE epochs kept"}
        present = [n for n in names if self.rounds and f"lgr_{n}" in self.rounds[0].column_names]
        rows = []
        for log in self.rounds:
            values = [log.mean(f"lgr_{n}") for n in present]
            if any(v is not None for v in values):
                rows.append(
                    [
                        f"end of {log.task} (round {log.round})",
                        *("-" if v is None else v for v in values),
                    ]
                )
        if not rows:
            return ""
        headers = ["", *(names[n] for n in present)]
        return "replay fidelity (0 = the real latents):\n" + table(headers, rows)

    def task_summary(self) -> str:
        """After each task: scores on all tasks seen so far, and each past task's forgetting
        (positive: forgotten; loss/RMSE now - then, PCC then - now)."""
        tasks = list(self.config.continual.tasks)
        rows = []
        for k, after in enumerate(self.after_tasks):
            seen = "+".join(tasks[: k + 1])
            row = [
                f"after {tasks[k]}",
                seen,
                *(after[f"after_task{k + 1}/test/{m}"] for m in ("loss", "rmse", "pcc")),
            ]
            forgot = [
                f"{t}: RMSE {after[f'after_task{k + 1}/forgetting/{t}/rmse']:+.3f} "
                f"PCC {after[f'after_task{k + 1}/forgetting/{t}/pcc']:+.3f}"
                for t in tasks[:k]
            ]
            rows.append([*row, "; ".join(forgot) or "-"])
        return table(["task", "tested on", "loss", "RMSE", "PCC", "forgetting"], rows)


def _human_bytes(n: float | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def _epoch_counter(bar: Progress, total: int):
    """A ``progress(client, epoch)`` callback that advances ``bar`` by one epoch per call
    (plugins may run more or fewer epochs than planned: the bar never overflows)."""
    done = itertools.count(1)
    return lambda client, epoch: bar(min(next(done), total), total)


def make_fabric(config: ExperimentConfig):
    from lightning.fabric import Fabric
    from lightning.fabric.strategies import DDPStrategy

    rt = config.runtime
    accelerator = "cuda" if rt.accelerator == "gpu" else rt.accelerator
    strategy = "auto"
    if rt.world_size > 1:
        # Models are never wrapped in DDP (clients train independently); buffers must
        # not be broadcast between processes either.
        strategy = (
            DDPStrategy(start_method="spawn", broadcast_buffers=False)
            if rt.launcher == "ddp_spawn"
            else DDPStrategy(broadcast_buffers=False)
        )
    return Fabric(
        accelerator=accelerator,
        devices=rt.devices,
        num_nodes=rt.num_nodes,
        strategy=strategy,
        precision=config.train.precision,
    )


def run_experiment(
    config: ExperimentConfig,
    *,
    parent_run_id: str | None = None,
    tags: dict[str, str] | None = None,
    echo=None,
    on_round=None,
) -> ExperimentResult | None:
    """Run ``config`` end to end; the result in rank 0, ``None`` in other processes.

    ``on_round(round, metrics)`` (rank 0, after each round is logged) may raise to stop the
    run, e.g. a sweep's pruner: the run is then ended KILLED if the exception has
    ``mlflow_status = "KILLED"``, FAILED otherwise, keeping what was logged."""
    from lightning.fabric.connector import _is_using_cli

    echo = echo or functools.partial(print, flush=True)  # progress must reach logs at once
    fabric = make_fabric(config)
    if config.runtime.world_size == 1 or _is_using_cli():
        return _main(fabric, config, parent_run_id, tags, echo, on_round)
    return fabric.launch(_main, config, parent_run_id, tags, echo, on_round)


def _main(
    fabric, config: ExperimentConfig, parent_run_id, tags, echo, on_round=None
) -> ExperimentResult | None:
    import torch
    from lightning.fabric import seed_everything

    from fedlgr.continual.forgetting import ForgettingTracker
    from fedlgr.continual.schedule import schedule
    from fedlgr.data.dataset import load_scenes
    from fedlgr.data.splits import make_split
    from fedlgr.tracking.mlflow_run import Tracker
    from fedlgr.tracking.plots import curves_png

    rank0 = fabric.global_rank == 0
    say = echo if rank0 else (lambda *a, **k: None)
    if fabric.device.type == "cpu":
        torch.set_num_threads(torch_threads(config, fabric.world_size // config.runtime.num_nodes))
    seed_everything(config.seed, verbose=False)
    start = time.perf_counter()
    scenes = load_scenes(config.data)
    split = make_split(scenes.table, config.data)
    orchestrator = Orchestrator(fabric, config, scenes, split)
    tracker = Tracker(config, tags, parent_run_id) if rank0 and config.tracking.enabled else None
    result = ExperimentResult(config, run_id=tracker.run_id if tracker else None)
    plan = (
        f"{len(config.continual.tasks)} tasks ({', '.join(config.continual.tasks)}) x "
        f"{config.continual.rounds_per_task} rounds"
        if config.continual.tasks
        else f"{config.federated.rounds} rounds"
    )
    say(
        f"{config.run_name}: {plan} x {config.train.epochs} local epochs, "
        f"{config.data.clients} clients, {len(split.train)} training / {len(split.test)} test "
        "scenes" + (f", {fabric.world_size} processes" if fabric.world_size > 1 else "")
    )
    tasks = list(config.continual.tasks)
    steps = schedule(config)
    forgetting = ForgettingTracker(tasks)
    total = len(steps)
    try:
        for step in steps:
            round_, k = step.round, step.task
            show = rank0 and config.runtime.progress
            label = f"round {round_}/{total}" + (f" (task {tasks[k]})" if tasks else "")
            with Progress(f"{label}, client epochs", "epoch", show) as bar:
                epochs = len(orchestrator.clients) * config.train.epochs
                log = orchestrator.run_round(
                    round_, k, step.first_of_task, step.last_of_task, _epoch_counter(bar, epochs)
                )
            result.rounds.append(log)
            metrics = {**log.metrics(), **forgetting.forgetting(log)}
            if step.last_of_task:
                metrics.update(forgetting.end_of_task(log, k))
                result.after_tasks = forgetting.after
            if tracker is not None:
                tracker.log_round(round_, metrics)
            loss, rmse, pcc = (log.mean(f"test_{m}") for m in ("loss", "rmse", "pcc"))
            say(
                f"{label}: loss {loss:.3f}  RMSE {rmse:.3f}  PCC {pcc:.3f}  "
                f"CPU {log.mean('cpu_s'):.1f} s/client  ({log.seconds:.1f} s)"
            )
            if on_round is not None and rank0:
                on_round(round_, metrics)
    except BaseException as err:
        if tracker is not None:
            tracker.save_results(
                result.rows(), curves_png(result.rows()) if result.rounds else None
            )
            tracker.log_summary(result.cost_means())
            killed = (
                isinstance(err, KeyboardInterrupt) or getattr(err, "mlflow_status", "") == "KILLED"
            )
            tracker.fail(interrupted=killed)
        raise
    result.seconds = time.perf_counter() - start
    if tracker is not None:
        tracker.save_results(result.rows(), curves_png(result.rows()))
        tracker.log_summary(result.cost_means())
        tracker.finish()
    if not rank0:
        return None
    say(f"\n{config.run_name} after {total} rounds ({result.seconds:.0f} s):")
    say(result.summary())
    return result
