"""EWC, MAS and SI as published (issue 48). Run: ``uv run python bench/ewc.py`` (~3 min on one
core; ``--quick``: a smoke run of ~30 s).

Three parts, each printed as a table:

1. **Cost at a task's end** (one thread): the seconds to estimate EWC's Fisher and MAS's
   importance over one client's task (``--scenes`` scenes), per mini-batch (the form before
   issue 48) and per scene (as published, ``torch.func`` per-scene gradients), on the
   descriptors' MLP and on the demo's half-width MobileNetV2 at 128 px.
2. **How far the mini-batch forms were from the published ones**, on the descriptors' MLP
   trained on the circle scenes of the synthetic living room: per parameter tensor, the
   ratio of the batch form's importance to the per-scene one (median and range over every
   weight), EWC at ``--ratio-batch`` (8, as in the issue) and MAS at 16.
3. **Forgetting** on the synthetic descriptors with the Table II 2-client preset
   (``conf/experiment/table2/clients2_noaug.yaml``: circle then arrow, 5 rounds x 10 epochs
   per task; MLP root, random init): FedRoot-FT, then FedRoot-EWC at every lambda of
   ``--lambdas`` with the published Fisher and with ``continual.ewc.fisher=batch``, on every
   seed of ``--seeds``: circle RMSE and PCC after Task 1, their forgetting after Task 2
   (positive: circle got worse), arrow after Task 2, and the final test RMSE (the objective
   of ``sweeps/ewc.yaml``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

# torch, scipy and fedlgr are imported inside the functions, as in bench/fcl.py: ``--help``
# answers before they load.
LAMBDAS = [1.0, 10.0, 100.0, 1000.0, 10000.0, 100000.0]
FORMS = {"per scene": "empirical", "batch (before)": "batch"}


def cost(scenes: int) -> list[list]:
    """Seconds per importance estimate over ``scenes`` scenes, batch form and per scene."""
    import numpy as np
    import torch

    from fedlgr.core.continual.ewc import fisher
    from fedlgr.core.continual.mas import output_norm_importance
    from fedlgr.core.data.augment import SceneBatches
    from fedlgr.core.models.scholar import MLPRoot, MobileNetRoot, Scholar, Top

    rows = []
    torch.manual_seed(0)
    for name, root, shape, dtype in (
        ("MLP (descriptors)", MLPRoot(), (29,), torch.float32),
        ("MobileNetV2 x0.5, 128 px", MobileNetRoot(width=0.5), (3, 128, 128), torch.uint8),
    ):
        model = Scholar(root, Top(root.out_dim)).to(memory_format=torch.channels_last)
        if dtype == torch.uint8:
            x = torch.randint(0, 256, (scenes, *shape), dtype=dtype)
        else:
            x = torch.rand(scenes, *shape)
        batches = SceneBatches(
            x, torch.rand(scenes, 8) * 4 + 1, np.arange(scenes), 16, shuffle=False
        )
        for label, run in (
            ("EWC Fisher", lambda k, m=model, b=batches: fisher(m, b, k)),
            (
                "MAS importance",
                lambda k, m=model, b=batches: output_norm_importance(
                    m, b, kind="batch" if k == "batch" else "sample"
                ),
            ),
        ):
            seconds = {}
            for kind in ("batch", "empirical"):
                run(kind)  # warm-up: vmap's first call traces
                start = time.process_time()
                run(kind)
                seconds[kind] = time.process_time() - start
            rows.append(
                [
                    name,
                    label,
                    seconds["batch"],
                    seconds["empirical"],
                    seconds["empirical"] / seconds["batch"],
                ]
            )
    return rows


def trained_mlp(data: Path, epochs: int):
    """The descriptors' scholar trained on the circle training scenes, and those scenes."""
    import numpy as np
    import torch

    from fedlgr.core.data.augment import SceneBatches
    from fedlgr.core.models.scholar import MLPRoot, Scholar, Top
    from fedlgr.shell.data.ratings import read_ratings

    table = read_ratings(data)
    x = torch.as_tensor(table.features[table.circle], dtype=torch.float32)
    y = torch.as_tensor(table.targets[table.circle], dtype=torch.float32)
    torch.manual_seed(0)
    root = MLPRoot()
    model = Scholar(root, Top(root.out_dim))
    optimizer = model.configure_optimizers()
    batches = SceneBatches(x, y, np.arange(len(x)), 16, seed=0)
    for _ in range(epochs):
        for xb, yb in batches:
            loss = torch.nn.functional.mse_loss(model(xb), yb)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return model, x, y


def ratios(data: Path, epochs: int, ewc_batch: int) -> list[list]:
    """Batch-form importance over per-scene importance, per weight: median, 5th and 95th
    percentile, and Spearman's rank correlation between the two."""
    import numpy as np
    import torch
    from scipy.stats import spearmanr

    from fedlgr.core.continual.ewc import fisher
    from fedlgr.core.continual.mas import output_norm_importance
    from fedlgr.core.data.augment import SceneBatches

    model, x, y = trained_mlp(data, epochs)
    rows = []
    for label, batch, estimate in (
        ("EWC Fisher", ewc_batch, lambda b, k: fisher(model, b, "batch" if k else "empirical")),
        (
            "MAS importance",
            16,
            lambda b, k: output_norm_importance(model, b, kind="batch" if k else "sample"),
        ),
    ):
        batches = SceneBatches(x, y, np.arange(len(x)), batch, shuffle=False)
        old, new = estimate(batches, True), estimate(batches, False)
        a = torch.cat([old[n].flatten() for n in old]).double().numpy()
        b = torch.cat([new[n].flatten() for n in new]).double().numpy()
        keep = b > 0
        r = a[keep] / b[keep]
        rows.append(
            [
                label,
                batch,
                float(np.median(r)),
                float(np.percentile(r, 5)),
                float(np.percentile(r, 95)),
                float(spearmanr(a[keep], b[keep]).statistic),
            ]
        )
    return rows


def forgetting(data: Path, work: Path, seeds: list[int], lambdas: list[float], extra: list[str]):
    from fedlgr.shell.config import CONF_DIR, load_config
    from fedlgr.shell.run.experiment import run_experiment

    common = [
        f"data.path={data}",
        f"data.cache_dir={work / 'cache'}",
        "data.modality=features",
        "data.crop=null",
        "model.root=mlp",
        "model.weights=none",
        f"tracking.uri=sqlite:///{work / 'mlflow.db'}",
        "tracking.checkpoint=0",
        "runtime.progress=false",
        *extra,
    ]
    runs = [("FedRoot-FT", "-", None, [])]
    for form, fisher in FORMS.items():
        runs += [
            (
                "FedRoot-EWC",
                form,
                lam,
                [f"continual.ewc.lambda_={lam}", f"continual.ewc.fisher={fisher}"],
            )
            for lam in lambdas
        ]
    rows = []
    for method, form, lam, overrides in runs:
        for seed in seeds:
            config = load_config(
                CONF_DIR / "experiment" / "table2" / "clients2_noaug.yaml",
                [*common, f"method={method}", f"seed={seed}", *overrides],
            )
            result = run_experiment(config, echo=lambda *a, **k: None)
            after1, after2 = result.after_tasks
            rows.append(
                [
                    method,
                    form,
                    "-" if lam is None else f"{lam:g}",
                    seed,
                    after1["after_task1/task/circle/rmse"],
                    after2["after_task2/forgetting/circle/rmse"],
                    after2["after_task2/forgetting/circle/pcc"],
                    after2["after_task2/task/arrow/rmse"],
                    result.rounds[-1].mean("test_rmse"),
                ]
            )
            print(f"  {method} {form} lambda {lam} seed {seed}: done", flush=True)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=192, help="one client's task (part 1)")
    parser.add_argument("--epochs", type=int, default=20, help="MLP training epochs (part 2)")
    parser.add_argument("--ratio-batch", type=int, default=8)
    parser.add_argument("--lambdas", nargs="+", type=float, default=LAMBDAS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--scenes-synth", type=int, default=1000)
    parser.add_argument("--quick", action="store_true", help="a smoke run: small and short")
    parser.add_argument("--set", nargs="*", default=[], metavar="key=value", dest="overrides")
    args = parser.parse_args()
    if args.quick:
        args.scenes, args.epochs, args.lambdas, args.seeds = 16, 2, [100.0], [0]
        args.scenes_synth = 120
        args.overrides += ["train.epochs=1", "continual.rounds_per_task=1"]

    import torch

    from fedlgr.shell.console import table
    from fedlgr.shell.data.synth import synthesize

    torch.set_num_threads(1)
    start = time.perf_counter()
    print(
        f"fedlgr EWC/MAS benchmark - {date.today()} - {platform.machine()}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}, 1 thread"
    )
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        data = work / "synth"
        synthesize(data, args.scenes_synth, seed=0, size=32, force=True)
        print(f"\n1. CPU seconds to estimate the importance over {args.scenes} scenes (batch 16)")
        print(table(["model", "importance", "batch s", "per scene s", "ratio"], cost(args.scenes)))
        print("\n2. batch form / per-scene form, per weight, on the MLP trained on circle")
        print(
            table(
                ["importance", "batch", "median", "5%", "95%", "rank corr."],
                ratios(data, args.epochs, args.ratio_batch),
            )
        )
        print(
            "\n3. Table II 2-client preset on the synthetic descriptors; forgetting > 0: "
            "circle got worse"
        )
        rows = forgetting(data, work, args.seeds, args.lambdas, args.overrides)
        headers = [
            "method",
            "Fisher",
            "lambda",
            "seed",
            "circle RMSE T1",
            "forget RMSE",
            "forget PCC",
            "arrow RMSE",
            "final RMSE",
        ]
        print(table(headers, rows))
        means = {}
        for row in rows:
            means.setdefault(tuple(row[:3]), []).append(row[4:])
        summary = [
            [*key, *(statistics.mean(col) for col in zip(*vals, strict=True))]
            for key, vals in means.items()
        ]
        print(f"\nmeans over seeds {args.seeds}")
        print(table([h for h in headers if h != "seed"], summary))
    print(f"\n{time.perf_counter() - start:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
