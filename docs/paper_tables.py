"""Regenerate docs/paper/: fedlgr's Tables I and II on the synthetic living room next to the
paper's published values (``fedlgr report --paper``).

    uv run python docs/paper_tables.py [--workdir DIR]

Synthesises 1000 scenes (seed 7) if absent, runs every Table I method (10 rounds) and
every Table II method (5 rounds per task) at 2 and 10 clients without augmentation on the
scenes' descriptors (`conf/debug/fast.yaml`'s small MLP root: seconds per run, where the
paper trained an ImageNet MobileNetV2 on MANNERS-DB's images for hours), each into one
MLflow experiment, then writes the report with the paper's rows to docs/paper/. The two are
the same methods and protocol on other data and another root: they can be read side by
side for rankings, not compared in value.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from fedlgr.shell.config import CONF_DIR, FCL_METHODS, METHODS, load_config
from fedlgr.shell.data.synth import synthesize
from fedlgr.shell.report import make_report
from fedlgr.shell.run.experiment import run_experiment

DOCS = Path(__file__).resolve().parent
FAST = CONF_DIR / "debug" / "fast.yaml"
EXPERIMENT = "paper-side-by-side"


def runs(data: Path, store: str) -> None:
    common = [f"data.path={data}", f"tracking.uri={store}", f"tracking.experiment={EXPERIMENT}"]
    common += ["tracking.system_metrics=false", "tracking.checkpoint=0"]
    for clients in (2, 10):
        for method in METHODS:
            plan = [f"method={method}", f"data.clients={clients}", "federated.rounds=10"]
            run_experiment(load_config(FAST, [*common, *plan]), show_runs=False)
        for method in (m for m in FCL_METHODS if not m.endswith("-FT")):
            plan = [f"method={method}", f"data.clients={clients}", "continual.rounds_per_task=5"]
            run_experiment(load_config(FAST, [*common, *plan]), show_runs=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path("paper-side-by-side"))
    args = parser.parse_args()
    data = args.workdir / "synth"
    if not data.exists():
        synthesize(data, 1000, 7, size=32)
    store = f"sqlite:///{args.workdir.resolve()}/mlflow.db"
    runs(data, store)
    out = args.workdir / "report"
    make_report(store, experiment=EXPERIMENT, out=out, log=False, paper=True)
    target = DOCS / "paper"
    target.mkdir(exist_ok=True)
    for name in ("table1.md", "table2.md"):
        shutil.copy(out / name, target / name)
    print(f"wrote {target}/table1.md and table2.md")


if __name__ == "__main__":
    main()
