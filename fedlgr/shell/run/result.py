"""What a run returns: every round's rows, the after-task figures, and the summary that
``fedlgr run`` prints at the end (the same for every runtime)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fedlgr.core.metrics import COST_KEYS, COSTS, SCORES, headline_scores
from fedlgr.core.records import RoundLog
from fedlgr.shell.config import ExperimentConfig
from fedlgr.shell.console import table

SHOWN_CLIENTS = 20  # the summary's per-client rows, up to this many clients


@dataclass
class ExperimentResult:
    config: ExperimentConfig
    rounds: list[RoundLog] = field(default_factory=list)
    run_id: str | None = None
    data_digest: str = ""  # of the data the run trained on (recorded in its checkpoints)
    seconds: float = 0.0
    after_tasks: list[dict[str, float]] = field(default_factory=list)  # FCL: per finished task
    # what recording cost (each round's logging and checkpoint, then the end's): kept, not logged
    tracking_seconds: list[float] = field(default_factory=list)
    checkpoint_seconds: list[float] = field(default_factory=list)
    results_seconds: float = 0.0

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
        """Costs per client per round averaged over clients and rounds (Tables III/IV); the server's
        and the paper's CPU figure where the server measured itself."""
        out = {}
        for key in COST_KEYS:
            column = np.concatenate([r.column(key) for r in self.rounds]) if self.rounds else []
            if len(column) and not np.isnan(column).all():
                out[f"mean/{key}"] = float(np.nanmean(column))
        server = [r.server for r in self.rounds if "cost/server_cpu_s" in r.server]
        if server and len(server) == len(self.rounds):
            cpu, n = sum(s["cost/server_cpu_s"] for s in server), len(server)
            out["mean/cost/server_cpu_s"] = cpu / n
            out["mean/cost/server_wall_s"] = sum(s["cost/server_wall_s"] for s in server) / n
            # the paper's CPU figure: the server process's CPU / (clients x rounds), docs/methods.md
            out["mean/cost/paper_cpu_s"] = cpu / (len(self.rounds[0].table) * n)
        return out

    def summary(self) -> str:
        """Final per-client scores; costs averaged over all rounds (as Table III reports them);
        FCL: the scores after each task and the forgetting too."""
        last = self.final
        scores = [f"test/{s.name}" for s in SCORES]
        costs = [c for c in COSTS if c.summary]
        # Over the rounds a client took part in (a robot that dropped out has NaN rows).
        per_round = {c.key: np.stack([r.column(c.key) for r in self.rounds]) for c in costs}
        clients = len(last.table)
        # a figure measured in no round (a client not scored) shows as "-"
        shown = [_dash] * len(scores)
        shown += [_human_bytes if c.key.startswith("cost/bytes") else _dash for c in costs]
        rows = [
            [f"client {i}", *(float(last.column(n)[i]) for n in scores)]
            + [_nanmean(per_round[c.key][:, i]) for c in costs]
            for i in range(clients if clients <= SHOWN_CLIENTS else 0)
        ]
        rows.append([last.statistic, *(last.mean(n) for n in scores)])
        rows[-1] += [_nanmean(per_round[c.key]) for c in costs]
        rows = [[row[0], *(f(v) for f, v in zip(shown, row[1:], strict=True))] for row in rows]
        headers = ["client", *(s.label for s in SCORES), *(c.summary for c in costs)]
        text = table(headers, rows) + self._scored_note()
        if self.after_tasks:
            text += "\n\n" + self.task_summary()
        for section in (self.replay_fidelity(), self.latent_drift(), self.privacy()):
            if section:
                text += "\n\n" + section
        return text

    def _scored_note(self) -> str:
        """What the summary's rows stand for where they are not every client's scores."""
        last, evaluate = self.final, self.config.federated.evaluate
        clients = len(last.table)
        first = f"test/{headline_scores()[0].name}"  # NaN for a client not scored
        scored = int((~np.isnan(last.column(first))).sum())
        notes = []
        if clients > SHOWN_CLIENTS:
            notes.append(f"{clients} clients: each one's row is in results.csv")
        if scored < clients:
            notes.append(
                f"test scores: the mean over the {scored} clients scored in the last round "
                f"(federated.evaluate={evaluate})"
            )
        left_out = int((~last.counted).sum())
        if last.byzantine:
            apart = ", ".join(
                f"{s.label} {v:.3f}"
                for s in headline_scores()
                if (v := last.apart(f"test/{s.name}")) is not None
            )
            named = ", ".join(map(str, last.byzantine))
            notes.append(
                f"{last.statistic}: of the clients that count, not the {len(last.byzantine)} "
                f"simulated attackers (client {named}{': ' + apart if apart else ''})"
            )
        if left_out > len(last.byzantine):
            notes.append(
                f"{last.statistic}: without the clients whose upload the last round refused"
            )
        if last.statistic != "mean":
            notes.append(
                f"{last.statistic}: robots' scores, which the server cannot check, by "
                f"{self.config.federated.strategy}'s robust statistic (docs/deployment.md)"
            )
        return "".join(f"\n{n}" for n in notes)

    def privacy(self) -> str:
        """Client-level DP: the epsilon the run spent, at its delta, after its rounds."""
        dp = self.config.federated.dp
        if not (dp.enabled and self.rounds):
            return ""
        spent = self.final.server.get("privacy/epsilon", math.inf)
        clip = self.final.server.get("privacy/clip", dp.clip)
        return (
            f"client-level DP: epsilon {spent:.3f} at delta {dp.delta:g} after "
            f"{len(self.rounds)} rounds (noise multiplier {dp.noise_multiplier:g}, "
            f"{dp.clipping} clipping, clip norm {clip:.4g} in the last round)"
        )

    def latent_drift(self) -> str:
        """FedLGR: the root's latent drift after each round of a later task, mean over
        clients (docs/fedlgr.md, "How FedLGR works here")."""
        names = {
            "drift": "current scenes",
            "drift_residual": "after the map",
            "drift_past": "past scenes (true)",
            "drift_past_residual": "past, after the map",
        }
        title = "latent drift since the task's start (FD, 0 = none)"
        # columns nothing was measured in (no compensation: no residuals) are left out
        return self._lgr_table(title, names, "round {round} ({task})", measured_only=True)

    def replay_fidelity(self) -> str:
        """FedLGR: the replay's fidelity at each task end, mean over clients (docs/fedlgr.md)."""
        names = {"fd_latent": "FD latents", "recon_mse": "recon MSE (held-out)"}
        names |= {"fd_labels": "FD labeller outputs", "vae_epochs": "VAE epochs kept"}
        title = "replay fidelity (0 = the real latents)"
        return self._lgr_table(title, names, "end of {task} (round {round})")

    def _lgr_table(
        self, title: str, names: dict[str, str], label: str, measured_only: bool = False
    ) -> str:
        """``title`` and a row per round that measured any of the ``lgr/`` figures ``names``."""
        present = [n for n in names if self.rounds and f"lgr/{n}" in self.rounds[0].keys]
        if measured_only:
            present = [
                n for n in present if any(r.mean(f"lgr/{n}") is not None for r in self.rounds)
            ]
        rows = []
        for log in self.rounds:
            values = [log.mean(f"lgr/{n}") for n in present]
            if any(v is not None for v in values):
                row = label.format(round=log.round, task=log.task)
                rows.append([row, *("-" if v is None else v for v in values)])
        headers = ["", *(names[n] for n in present)]
        return f"{title}:\n{table(headers, rows)}" if rows else ""

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
                *(after[f"after_task{k + 1}/test/{s.name}"] for s in SCORES),
            ]
            forgot = [
                f"{t}: "
                + " ".join(
                    f"{s.label} {after[f'after_task{k + 1}/forgetting/{t}/{s.name}']:+.3f}"
                    for s in headline_scores()
                )
                for t in tasks[:k]
            ]
            rows.append([*row, "; ".join(forgot) or "-"])
        headers = ["task", "tested on", *(s.label for s in SCORES), "forgetting"]
        return table(headers, rows)


def _nanmean(values) -> float:
    """The mean of the values that are not NaN; NaN, without numpy's warning, if none are."""
    present = np.asarray(values, dtype=float)
    present = present[~np.isnan(present)]
    return float(present.mean()) if present.size else math.nan


def _dash(value: float | None) -> object:
    return "-" if value is None or math.isnan(value) else value


def _human_bytes(n: float | None) -> str:
    if n is None or math.isnan(n):
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB"):  # binary units, named as such
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)
