"""FCL benchmark (issues 4, 9 and 19). Run: ``uv run python bench/fcl.py`` (~50 minutes on 2 cores).

On the synthetic living room (1000 scenes, 2 clients), Task 1 = circle then Task 2 = arrow,
``--rounds-per-task`` rounds of ``--epochs`` local epochs each, in each ``--modality``:
``image`` (128 px; a half-width MobileNetV2 root pretrained offline on the descriptors of
*other* synthetic scenes, seed 1000, no appropriateness labels - the stand-in for the paper's
ImageNet weights) and ``features`` (the MLP root over the 27 descriptors + 2 mode flags of
the same ``all_data.csv``, random init). On every seed of ``--seeds`` it runs the
``--seeded`` baselines (FedRoot-FT = FedRoot without a CL method, FedRoot-NR, FedRoot-EWC)
and the ``--lgr`` variants of FedLGR, each with its stored-latent oracle ("<label>
(stored)"): ``FedLGR`` at its defaults, ``FedLGR-paper`` (no drift control: the paper's
method), ``FedLGR-compensate``, ``FedLGR-distill``, ``FedLGR-blocks`` and ``FedLGR-freeze`` (one
drift control each, see LGR_VARIANTS); ``--variant LABEL=key=value,...`` adds one. The ``--methods``
(other Table II methods) run on the first seed. Prints per run the circle-test RMSE and
PCC after Task 1 and after Task 2, the forgetting (positive: circle got worse), arrow after
Task 2, the CPU seconds per client per round in Task 2 and FedLGR's latent drift after the
last round; then the Table IV rows that ``fedlgr report`` builds from the runs (all rounds),
and checks issue 19's targets per seed (see ``check``). ``--workdir`` keeps the data, the
pretrained root and the MLflow store (``mlflow.db``); ``--set key=value`` applies to every
run (e.g. ``continual.freeze_root_bn=true``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

SEEDED_BASELINES = ["FedRoot-FT", "FedRoot-NR", "FedRoot-EWC"]
OTHERS = [
    "FedAvg-EWC",
    "FedAvg-EWCOnline",
    "FedAvg-SI",
    "FedAvg-MAS",
    "FedAvg-NR",
    "FedRoot-EWCOnline",
    "FedRoot-SI",
    "FedRoot-MAS",
    "FedAvg-LwF",  # not in the paper (Li & Hoiem 2016, fedlgr/core/continual/lwf.py)
    "FedRoot-LwF",
]
# FedLGR's variants (issue 19): "FedLGR" is the method at its defaults (conf/continual/
# lgr.yaml); the others pin the drift controls; each has its stored-latent oracle (real past
# latents replayed instead of the generator's), "<label> (stored)".
LGR_VARIANTS = {
    "FedLGR": [],
    "FedLGR-paper": ["continual.lgr.drift=none", "continual.lgr.train_blocks=null"],
    "FedLGR-compensate": ["continual.lgr.drift=compensate", "continual.lgr.train_blocks=null"],
    "FedLGR-distill": ["continual.lgr.drift=distill", "continual.lgr.train_blocks=null"],
    "FedLGR-blocks": ["continual.lgr.drift=none", "continual.lgr.train_blocks=1"],
    "FedLGR-freeze": [  # replay at the freeze point, below the last two blocks
        "continual.lgr.drift=none",
        "continual.lgr.train_blocks=2",
        "continual.lgr.replay_layer=freeze",
        "continual.lgr.schedule=joint",
    ],
}
STORED = " (stored)"
TARGETS = {"cut": 0.60, "arrow": 0.02, "oracle": 0.03, "features_cut": 0.90}
DRIFT = ["drift", "drift_residual", "drift_past", "drift_past_residual"]


def variant(label: str) -> tuple[str, list[str]]:
    """(method, overrides) of a run label: a Table II method, a FedLGR variant, or either
    FedLGR's oracle (``... (stored)``)."""
    if label in LGR_VARIANTS:  # one given whole (--variant)
        return "FedLGR", LGR_VARIANTS[label]
    base = label.removesuffix(STORED)
    if base in LGR_VARIANTS:
        extra = LGR_VARIANTS[base] + (["continual.lgr.replay=stored"] if label != base else [])
        return "FedLGR", extra
    return label, []


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modality", nargs="+", default=["features", "image"])
    parser.add_argument("--methods", nargs="*", default=OTHERS, help="Table II methods, seed 0")
    parser.add_argument(
        "--seeded", nargs="*", default=SEEDED_BASELINES, help="baselines run on every seed"
    )
    parser.add_argument(
        "--lgr",
        nargs="*",
        default=list(LGR_VARIANTS),
        help=f"FedLGR variants run on every seed, each with its oracle ({', '.join(LGR_VARIANTS)})",
    )
    parser.add_argument("--no-oracles", action="store_true", help="skip the (stored) runs")
    parser.add_argument(
        "--variant",
        nargs="*",
        default=[],
        metavar="LABEL=key=value,...",
        help="an extra FedLGR variant (added to --lgr): its label and overrides",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--rounds-per-task", type=int, default=8)
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--width", type=float, default=0.5)
    parser.add_argument("--set", nargs="*", default=[], metavar="key=value", dest="overrides")
    parser.add_argument("--workdir", type=Path, default=None, help="keep data, root, runs here")
    args = parser.parse_args()

    from fedlgr.shell.machine import tune_allocator

    tune_allocator()
    import torch

    start = time.perf_counter()
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        outputs = [run_modality(m, work, args) for m in args.modality]
    print(
        f"\nfedlgr FCL benchmark - {date.today()} - {platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}; {time.perf_counter() - start:.0f} s in all"
    )
    for text, fails in outputs:
        print(text)
        failed += fails
    return 1 if failed else 0


def run_modality(modality: str, work: Path, args) -> tuple[str, int]:
    from fedlgr.shell.config import CONF_DIR, load_config
    from fedlgr.shell.data.synth import synthesize
    from fedlgr.shell.pretrain import synthetic_root
    from fedlgr.shell.run.experiment import run_experiment

    data = work / "synth"
    if not (data / "all_data.csv").is_file():
        synthesize(data, 1000, seed=0, size=args.size, force=True)
    uri = f"sqlite:///{work / 'mlflow.db'}"
    common = [
        f"data.path={data}",
        f"data.cache_dir={work / 'cache'}",
        f"train.epochs={args.epochs}",
        f"continual.rounds_per_task={args.rounds_per_task}",
        f"tracking.uri={uri}",
        "runtime.progress=false",
    ]
    if modality == "image":
        root = synthetic_root(
            work / "pretrain", width=args.width, size=args.size, cache_dir=work / "cache"
        )
        common += [f"data.image_size={args.size}", f"model.width={args.width}"]
        common += [f"model.weights={root}"]
    else:
        common += ["data.modality=features", "model.root=mlp"]
    for spec in args.variant:
        label, _, overrides = spec.partition("=")
        LGR_VARIANTS[label] = overrides.split(",") if overrides else []
        args.lgr.append(label)
    pairs = [[name] if name.endswith(STORED) else [name, name + STORED] for name in args.lgr]
    lgr = [v for pair in pairs for v in pair[: 1 if args.no_oracles else 2]]
    seeded = args.seeded + lgr
    runs = [(m, s) for m in seeded for s in args.seeds] + [(m, args.seeds[0]) for m in args.methods]
    results, saved = {}, {}
    # One MLflow experiment per invocation: Table IV averages every run of its experiment.
    stamp = time.strftime("%Y%m%d-%H%M%S")
    print(f"{modality}: MLflow experiment bench-fcl-{modality}-{stamp} in {uri}", flush=True)
    for label, seed in runs:
        method, extra = variant(label)
        # FedLGR's variants log to experiments of their own: fedlgr report averages runs per
        # method, so the Table IV experiment holds FedLGR at its defaults only.
        experiment = f"bench-fcl-{modality}-{stamp}"
        if label != "FedLGR" and method == "FedLGR":
            experiment += "-" + label.replace(" ", "").replace("(", "-").replace(")", "")
        config = load_config(
            CONF_DIR / "experiment" / "demo_fcl.yaml",
            [
                *common,
                f"method={method}",
                f"seed={seed}",
                *extra,
                *args.overrides,
                f"tracking.experiment={experiment}",
                f"tracking.run_name={label}-seed{seed}",
            ],
        )
        t = time.perf_counter()
        result = run_experiment(config, echo=lambda *a, **k: None)
        print(f"  {label} (seed {seed}): {time.perf_counter() - t:.0f} s", flush=True)
        results[label, seed] = result
        saved[f"{modality} {label} seed {seed}"] = {
            "after_tasks": result.after_tasks,
            "task2_cpu_s": task2_cpu(result),
            "drift": final_drift(result),
            "run_id": result.run_id,
        }
        with (work / f"fcl_results_{modality}.json").open("w") as f:
            json.dump(saved, f, indent=1)  # nothing lost if a later run fails
    return report(modality, results, args, uri, f"bench-fcl-{modality}-{stamp}", work)


def task2_cpu(result) -> float:
    """CPU seconds per client per round over the rounds of the last task."""
    last = result.config.continual.tasks[-1]
    return float(np.mean([log.mean("cpu_s") for log in result.rounds if log.task == last]))


def final_drift(result) -> dict[str, float | None]:
    """FedLGR's drift figures after the last round (mean over clients; None: not logged)."""
    last = result.rounds[-1]
    return {n: last.mean(f"lgr_{n}") if f"lgr_{n}" in last.column_names else None for n in DRIFT}


def report(
    modality: str, results: dict, args, uri: str, experiment: str, work: Path
) -> tuple[str, int]:
    from fedlgr.shell.cli.demo import forgetting_table
    from fedlgr.shell.console import table
    from fedlgr.shell.report import make_report

    runs = list(results.values())
    labels = {id(r): f"{label} seed {seed}" for (label, seed), r in results.items()}
    what = (
        f"synthetic data, 1000 scenes, 2 clients, circle then arrow, {args.rounds_per_task} "
        f"rounds x {args.epochs} local epochs per task, "
        + (
            f"{args.size} px, width-{args.width:g} MobileNetV2 pretrained on other scenes' "
            "descriptors"
            if modality == "image"
            else "descriptors (MLP root, random init)"
        )
        + (f"; {' '.join(args.overrides)}" if args.overrides else "")
    )
    text = [f"\n== {modality}: {what}; forgetting > 0: circle got worse\n"]
    text.append(forgetting_table(runs, lambda r: labels[id(r)]))
    text.append(
        "\nCPU s per client per round in Task 2 (this run, side by side), and FedLGR's latent "
        "drift after the last round (FD since Task 2's start; current scenes / after the "
        "compensation map / past-task scenes, the true drift / past, after the map):"
    )
    drift_rows = []
    for r in runs:
        drift = final_drift(r)
        drift_rows.append([labels[id(r)], task2_cpu(r), *(drift[n] for n in DRIFT)])
    headers = ["method", "CPU s", "drift", "residual", "true drift", "true residual"]
    text.append(table(headers, drift_rows))
    has_table2 = any(label == "FedLGR" or variant(label)[0] != "FedLGR" for label, _ in results)
    table4 = work / f"report-{experiment}" / "table4.md"
    if has_table2:  # the experiment is empty when only FedLGR's variants ran
        make_report(uri, experiment=experiment, log=False, out=table4.parent)
    if table4.is_file():
        text.append(f"\nfedlgr report --experiment {experiment}: Table IV (all rounds)")
        text.append(table4.read_text().strip())
    lines, failed = check(results, args.seeds, modality)
    return "\n".join(text + lines), failed


def check(results: dict, seeds: list[int], modality: str) -> tuple[list[str], int]:
    """Issue 19's targets per seed: FedLGR (its defaults) cuts FedRoot-FT's circle
    forgetting by >= 60% in RMSE and in PCC on the images (>= 90% in RMSE on the
    descriptors), learns arrow within 0.02 RMSE of FedRoot-FT, its stored oracle forgets
    <= 0.03 RMSE, and it costs no more CPU per client per round in Task 2 than FedRoot-NR;
    FedRoot-FT must forget beyond noise."""
    out, failed = ["\nchecks (FedLGR at its defaults):"], 0

    def forgot(r, metric):
        return r.after_tasks[1][f"after_task2/forgetting/circle/{metric}"]

    images = modality == "image"
    for s in seeds:
        ft, lgr, oracle, nr = (
            results.get((m, s)) for m in ("FedRoot-FT", "FedLGR", "FedLGR" + STORED, "FedRoot-NR")
        )
        if ft is None or lgr is None:
            out.append(f"  seed {s}: FedRoot-FT and FedLGR are needed for the checks")
            continue
        per_task = ft.config.continual.rounds_per_task
        circle = [log.mean("task_circle_rmse") for log in ft.rounds[:per_task]]
        changes = np.abs(np.diff(circle[-3:]))
        noise = float(changes.max()) if len(changes) else float("nan")  # nan: not measurable
        verdicts = [
            (
                f"FedRoot-FT forgets: RMSE {forgot(ft, 'rmse'):+.3f} > 3 x noise {noise:.3f}",
                forgot(ft, "rmse") > 3 * noise,
            ),
        ]
        target = TARGETS["cut"] if images else TARGETS["features_cut"]
        for metric in ("rmse", "pcc") if images else ("rmse",):
            if forgot(ft, metric) <= 0:  # nothing to cut: the check cannot pass
                verdicts.append((f"FedRoot-FT does not forget {metric.upper()}", False))
                continue
            cut = 1 - forgot(lgr, metric) / forgot(ft, metric)
            verdicts.append(
                (
                    f"FedLGR cuts {metric.upper()} forgetting by {cut:.0%} "
                    f"({forgot(lgr, metric):+.3f} vs {forgot(ft, metric):+.3f}; "
                    f"target >= {target:.0%})",
                    cut >= target,
                )
            )
        arrow = [r.after_tasks[1]["after_task2/task/arrow/rmse"] for r in (lgr, ft)]
        verdicts.append(
            (
                f"FedLGR arrow RMSE {arrow[0]:.3f} vs FedRoot-FT {arrow[1]:.3f} "
                f"(target <= +{TARGETS['arrow']})",
                arrow[0] - arrow[1] <= TARGETS["arrow"],
            )
        )
        if oracle is not None:
            verdicts.append(
                (
                    f"stored oracle forgets RMSE {forgot(oracle, 'rmse'):+.3f} "
                    f"(target <= {TARGETS['oracle']})",
                    forgot(oracle, "rmse") <= TARGETS["oracle"],
                )
            )
        if nr is not None and images:
            cpu = task2_cpu(lgr), task2_cpu(nr)
            verdicts.append(
                (
                    f"FedLGR Task-2 CPU {cpu[0]:.2f} s vs FedRoot-NR {cpu[1]:.2f} s (target <=)",
                    cpu[0] <= cpu[1],
                )
            )
        for text, ok in verdicts:
            failed += not ok
            out.append(f"  seed {s}: {text}: {'ok' if ok else 'MISSED'}")
    return out, failed


if __name__ == "__main__":
    sys.exit(main())
