"""Privacy benchmark (issue 38): what the shared part reveals, and what client-level DP
costs. Run: ``uv run python bench/privacy.py`` (~10 min on 2 cores; ``--quick``: a smoke
run of every step, what ``tests/test_privacy_bench.py`` runs).

1. **Membership inference on one round** (``bench/privacy_attack.py``: the attacks, their
   citations and the root-only attacker's top). 4 robots, 200 synthetic scenes (about 37
   training scenes each), 30 local epochs of fedlgr's ``ClientSide`` from the initial
   model (the MLP root over the descriptors, ``data.modality=features``); robot 0's
   training scenes against as many unseen test scenes. For the whole model (FedAvg) and the
   root only (FedRootAvg), the server sees robot 0's upload, the plain aggregate, or
   ``ServerSide``'s DP release (clip norm: the median of the round's update norms; noise
   multipliers ``--attack-noise``; 0: clipping alone). ROC AUC of the loss-difference and
   gradient-alignment scores, mean +- sd over ``--seeds``; epsilon of one release
   (``fedlgr.core.privacy.epsilon``, q = 1, delta 1e-5).
2. **Utility vs epsilon**: FedAvg and FedRootAvg through ``run_experiment`` (the path of
   ``fedlgr run``; tracking off) on 2000 synthetic scenes, 100 clients, fraction 0.5 (Poisson
   sampling under DP), 20 rounds of ``conf/debug/fast.yaml``'s features model, no DP and
   noise multipliers ``--noise``. Each method's clip norm is the median update norm of its
   round 1 without DP (seed 99, not one of the runs'; chosen on the private data itself: a
   deployment would choose it on public data or use adaptive clipping). Final test RMSE,
   PCC and CCC (mean over clients; mean +- sd over ``--seeds``) and the run's logged
   ``privacy/epsilon``.

Prints both tables (markdown) and writes ``privacy-features.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import matplotlib
import torch
from privacy_attack import ATTACKS, clip_norm, gradients, observations, scores, train_round
from privacy_attack import auc as attack_auc

from fedlgr.shell.config import CONF_DIR, load_config
from fedlgr.shell.data.synth import synthesize
from fedlgr.shell.run.experiment import run_experiment

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.ticker import NullFormatter

FULL = {
    "attack_scenes": 200,
    "attack_epochs": 30,
    "scenes": 2000,
    "clients": 100,
    "fraction": 0.5,
    "rounds": 20,
}
QUICK = {
    "attack_scenes": 120,
    "attack_epochs": 5,
    "scenes": 300,
    "clients": 20,
    "fraction": 0.5,
    "rounds": 3,
}
METHODS = {"full": "FedAvg", "root": "FedRootAvg"}
SHARED = {"full": "whole model", "root": "root only"}
FAST = CONF_DIR / "debug" / "fast.yaml"  # the descriptors' MLP ([16]), batch 8, lr 0.01


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run (the CI test's)")
    parser.add_argument("--seeds", nargs="+", type=int, default=None)
    parser.add_argument("--attack-noise", nargs="+", type=float, default=[0.0, 0.01, 0.3, 1.0])
    parser.add_argument("--noise", nargs="+", type=float, default=None)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "img")
    args = parser.parse_args(argv)
    sizes = QUICK if args.quick else FULL
    seeds = args.seeds or ([0] if args.quick else [0, 1, 2, 3, 4])
    noises = args.noise or ([1.0, 4.0] if args.quick else [0.5, 1.0, 2.0, 4.0])
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        attack = membership(work, sizes, seeds, args.attack_noise)
        utility_seeds = seeds[:3]  # 3 seeds: the utility runs are most of the time
        utility = utilities(work, sizes, utility_seeds, noises)
    print(
        f"\nfedlgr privacy benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}; "
        f"{time.perf_counter() - start:.0f} s in all\n"
    )
    print(f"Membership inference on one round (AUC, mean ± sd over seeds {seeds})\n")
    print(attack_table(attack))
    print(f"\nUtility vs epsilon (final round; mean ± sd over seeds {utility_seeds})\n")
    print(utility_table(utility))
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "privacy-features.png"
    plot(utility, sizes, path)
    print(f"\nplot: {path}")
    return 0


def synth(work: Path, scenes: int) -> Path:
    """``scenes`` synthetic scenes (32 px: only their descriptors are read)."""
    data = work / f"synth-{scenes}"
    if not (data / "all_data.csv").is_file():
        synthesize(data, scenes, seed=0, size=32, force=True)
    return data


# ---------------------------------------------------------------------- 1. the attack


def membership(work: Path, sizes: dict, seeds: list[int], noises: list[float]) -> list[dict]:
    """One row per (scope, observation): the one-round epsilon and each attack's AUCs."""
    data = synth(work, sizes["attack_scenes"])
    rows = {}
    for scope in ("full", "root"):
        settings = [
            f"data.path={data}",
            "data.modality=features",
            "model.root=mlp",
            "data.clients=4",
            f"federated.scope={scope}",
            f"train.epochs={sizes['attack_epochs']}",
            "train.batch_size=16",
            "runtime.progress=false",
        ]
        for seed in seeds:
            t = time.perf_counter()
            round_ = train_round(settings, seed)
            grads = gradients(round_)
            for name, (seen, eps) in observations(round_, noises).items():
                row = rows.setdefault((scope, name), {"scope": scope, "seen": name, "eps": eps})
                for attack, score in scores(round_, seen, grads).items():
                    row.setdefault(attack, []).append(attack_auc(score, round_.members))
            print(
                f"  attack {SHARED[scope]}, seed {seed}: clip {clip_norm(round_):.2f}, "
                f"{time.perf_counter() - t:.0f} s",
                flush=True,
            )
    return list(rows.values())


def attack_table(rows: list[dict]) -> str:
    """The membership inference table, markdown."""
    head = "| shared | the server sees | epsilon (one round) | " + " | ".join(
        f"{a} AUC" for a in ATTACKS
    )
    lines = [head + " |", "|---" * (3 + len(ATTACKS)) + "|"]
    for row in rows:
        seen = {"upload": "robot's upload", "aggregate": "plain aggregate"}.get(row["seen"])
        clipped = "clipped mean, no noise (z=0)"
        seen = seen or (clipped if row["seen"] == "DP z=0" else f"DP release, {row['seen'][3:]}")
        cells = [SHARED[row["scope"]], seen, _eps(row["eps"])]
        cells += [_spread(row[a], 3) for a in ATTACKS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------- 2. utility


def utilities(work: Path, sizes: dict, seeds: list[int], noises: list[float]) -> list[dict]:
    """One row per (method, noise multiplier; None: no DP): clip, epsilon and scores."""
    data = synth(work, sizes["scenes"])
    common = [
        f"data.path={data}",
        f"data.clients={sizes['clients']}",
        f"federated.fraction={sizes['fraction']}",
        f"federated.rounds={sizes['rounds']}",
        "tracking.enabled=false",
    ]
    rows = []
    for method in METHODS.values():
        clip = clip_norm(train_round([*common, f"method={method}"], 99, base=FAST))
        for noise in [None, *noises]:
            dp = [] if noise is None else [f"federated.dp.clip={clip}"]
            dp += [] if noise is None else [f"federated.dp.noise_multiplier={noise}"]
            row = {"method": method, "noise": noise, "clip": clip if dp else None, "eps": None}
            for seed in seeds:
                config = load_config(FAST, [*common, f"method={method}", f"seed={seed}", *dp])
                last = run_experiment(config, echo=lambda *a, **k: None).rounds[-1]
                for score in ("rmse", "pcc", "ccc"):
                    row.setdefault(score, []).append(last.mean(f"test/{score}"))
                row["eps"] = last.server.get("privacy/epsilon")
            print(f"  utility {method}, noise {noise}: done", flush=True)
            rows.append(row)
    return rows


def utility_table(rows: list[dict]) -> str:
    """The utility table, markdown."""
    lines = [
        "| method | noise multiplier | clip | epsilon (all rounds) | RMSE | PCC | CCC |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        noise = "no DP" if row["noise"] is None else f"{row['noise']:g}"
        clip = "—" if row["clip"] is None else f"{row['clip']:.3f}"
        scores_ = [_spread(row[s], 3) for s in ("rmse", "pcc", "ccc")]
        cells = [row["method"], noise, clip, _eps(row["eps"]), *scores_]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows: list[dict], sizes: dict, path: Path) -> None:
    """RMSE and PCC against epsilon for both methods; no DP as a dashed line."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, score, label in zip(axes, ("rmse", "pcc"), ("test RMSE", "test PCC"), strict=True):
        for i, method in enumerate(METHODS.values()):
            colour = f"C{i}"
            dp = [r for r in rows if r["method"] == method and r["noise"] is not None]
            dp.sort(key=lambda r: r["eps"])
            ax.errorbar(
                [r["eps"] for r in dp],
                [statistics.mean(r[score]) for r in dp],
                yerr=[_sd(r[score]) for r in dp],
                marker="o",
                capsize=3,
                color=colour,
                label=f"{method}, DP",
            )
            for r in dp:
                ax.annotate(f"z={r['noise']:g}", (r["eps"], statistics.mean(r[score])), fontsize=7)
            clean = next(r for r in rows if r["method"] == method and r["noise"] is None)
            ax.axhline(
                statistics.mean(clean[score]), ls="--", color=colour, label=f"{method}, no DP"
            )
        ax.set_xscale("log")
        ticks = sorted({r["eps"] for r in rows if r["noise"] is not None})
        ax.set_xticks(ticks, [f"{e:.2g}" for e in ticks])
        ax.xaxis.set_minor_formatter(NullFormatter())
        if score == "rmse":  # a wrecked model's RMSE runs to 100s: log scale
            ax.set_yscale("log")
        ax.set_xlabel("epsilon after all rounds (delta = 1e-5)")
        ax.set_ylabel(label)
        ax.legend(fontsize=8, loc="upper right" if score == "rmse" else "lower right")
    fig.suptitle(
        f"Client-level DP on the descriptors: {sizes['clients']} clients, fraction "
        f"{sizes['fraction']:g}, {sizes['rounds']} rounds"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---------------------------------------------------------------------- figures


def _sd(values: list[float]) -> float:
    return statistics.stdev(values) if len(values) > 1 else 0.0


def _spread(values: list[float], digits: int) -> str:
    """``mean ± sd`` (the mean alone for one value)."""
    mean = statistics.mean(values)
    if len(values) == 1:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {_sd(values):.{digits}f}"


def _eps(value: float | None) -> str:
    """An epsilon for the tables: "—" without DP, "inf" for clipping alone."""
    if value is None:
        return "—"
    return "inf" if math.isinf(value) else f"{value:.3g}"


if __name__ == "__main__":
    sys.exit(main())
