"""``fedlgr demo``: FedAvg vs FedRootAvg on a synthetic living room, made if absent; ``--fcl``
shows forgetting instead: FedRoot-FT vs FedLGR, circle then arrow."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import typer

from fedlgr.core.metrics import SCORES, headline_scores
from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.checks.stores import check_reachable
from fedlgr.shell.cli.verb import Overrides, TrackingUri, Verbs
from fedlgr.shell.console import Progress, table
from fedlgr.shell.tracking.uri import given_uri

DEFAULT_DATA = Path("data/manners-synth")
DEMO_CONFIG = conf.CONF_DIR / "experiment" / "demo.yaml"
FCL_CONFIG = conf.CONF_DIR / "experiment" / "demo_fcl.yaml"
METHODS = ("FedAvg", "FedRootAvg")
FCL_METHODS = ("FedRoot-FT", "FedLGR")
FEATURES_FCL = ["data.modality=features", "model.root=mlp", "continual.rounds_per_task=8"]
# The forgetting table's column groups: (heading, key prefix, when), a column per headline score.
FORGETTING_GROUPS = (
    ("circle", "after_task1/task/circle", "T1"),
    ("circle", "after_task2/task/circle", "T2"),
    ("forgot", "after_task2/forgetting/circle", ""),
    ("arrow", "after_task2/task/arrow", "T2"),
)

app = Verbs()


@app.command("demo", short_help="the main job: FedAvg vs FedRootAvg on the embedded synthetic data")
def demo(
    overrides: Overrides = (),
    data: Annotated[Path, typer.Option(help="dataset folder")] = DEFAULT_DATA,
    scenes: Annotated[int, typer.Option(help="scenes to synthesise if absent")] = 1000,
    seed: Annotated[int, typer.Option(help="seed of the data and the runs")] = 0,
    tracking_uri: TrackingUri = None,
    fcl: Annotated[
        bool,
        typer.Option(
            help="show forgetting instead: FedRoot without a CL method vs FedLGR, circle then "
            "arrow (see --modality)",
        ),
    ] = False,
    modality: Annotated[
        Literal["features", "image"],
        typer.Option(
            help="--fcl: the descriptors (MLP root, about 40 s) or the images (a root "
            "pretrained once, about 4 minutes)"
        ),
    ] = "features",
    pretrain_scenes: Annotated[
        int, typer.Option(help="--fcl: scenes (of another seed) the root is pretrained on")
    ] = 2000,
    pretrain_images: Annotated[
        int, typer.Option(help="--fcl: augmented images the root is pretrained on")
    ] = 16000,
) -> None:
    """Synthesise the living room if absent, then train FedAvg and FedRootAvg on it
    (conf/experiment/demo.yaml), tracked in MLflow, and print a comparison table.
    Overrides (key=value) apply to both runs."""
    check_reachable(given_uri(tracking_uri, overrides))  # before loading torch
    from fedlgr.shell.data.synth import synthesize  # lazy: PIL and numpy, after the check (1 s)

    if not (data / "all_data.csv").is_file():
        print(f"no dataset in {data}: synthesising {scenes} scenes (seed {seed})")
        with Progress("synthesising", unit="scene") as bar:
            synthesize(data, scenes, seed, force=True, progress=bar)
    overrides = [f"data.path={data}", f"seed={seed}", *overrides]
    if tracking_uri:
        overrides.append(f"tracking.uri={tracking_uri}")
    if fcl:
        base = _fcl_base(overrides, data, seed, modality, pretrain_scenes, pretrain_images)
        results = _run_each(FCL_CONFIG, FCL_METHODS, [*base, *overrides])
        print(
            f"\nForgetting on {data} ({modality}): Task 1 = circle, then Task 2 = arrow "
            "(mean over clients; forgetting > 0: circle got worse)"
        )
        print(forgetting_table(results))
    else:
        results = _run_each(DEMO_CONFIG, METHODS, overrides)
        rows = []
        for r in results:
            costs = r.cost_means()  # per client per round, over all rounds
            spent = [costs["mean/cost/cpu_s"], f"{costs['mean/cost/bytes_up'] / 2**20:.2f} MiB"]
            scores = [r.final.mean(f"test/{s.name}") for s in SCORES]
            rows.append([r.config.method_name, *scores, *spent, f"{r.seconds:.0f}"])
        print(
            f"\nFedAvg vs FedRootAvg on {data} after {results[0].config.federated.rounds} rounds "
            "(test scores: mean over clients; costs: per client per round, mean over the rounds)"
        )
        print(table(["method", *(s.label for s in SCORES), "CPU s", "upload", "run s"], rows))
    print_runs_hint(results)


def _run_each(path: Path, methods: tuple[str, ...], overrides: list[str]) -> list:
    from fedlgr.shell.run.experiment import run_experiment  # lazy: torch and Fabric

    results = []
    for method in methods:
        config = conf.load_config(path, [*overrides, f"method={method}"])
        print()
        results.append(run_experiment(config, show_runs=False))
    return results


def _fcl_base(
    overrides: list[str], data: Path, seed: int, modality: str, scenes: int, images: int
) -> list[str]:
    """``--fcl``'s overrides: the descriptors, or the images from a root pretrained on
    ``images`` augmented images of ``scenes`` other scenes."""
    if modality == "features":
        return FEATURES_FCL
    from fedlgr.shell.pretrain import synthetic_root  # lazy: torch

    probe = conf.load_config(FCL_CONFIG, overrides)
    root = synthetic_root(
        data.parent / "pretrain",
        seed=seed,
        scenes=scenes,
        width=probe.model.width,
        images=images,
        size=probe.data.image_size,
        cache_dir=probe.data.cache_dir,
        progress=Progress,  # a bar (or log lines) for each stage
    )
    return [f"model.weights={root}"]


def print_runs_hint(results) -> None:
    """Where to compare the runs in MLflow's UI (link, and how to start it)."""
    # lazy: filelock, which fedlgr --help does without
    from fedlgr.shell.tracking.mlflow_run import open_client, tracking_uri
    from fedlgr.shell.tracking.store import runs_hint

    tracked = [r for r in results if r.run_id]
    if tracked:
        uri = tracking_uri(tracked[0].config)
        run = open_client(uri).get_run(tracked[0].run_id)
        print("\n" + runs_hint(uri, run.info.experiment_id))


def forgetting_table(results, label=lambda r: r.config.method_name) -> str:
    """Per run and headline score: circle after Task 1 and after Task 2, its forgetting,
    arrow after Task 2."""
    scores = headline_scores()
    headers = ["method"]
    for name, _, when in FORGETTING_GROUPS:
        for i, s in enumerate(scores):
            # the group's name on its first column ("circle RMSE T1", "PCC T1"), or on
            # each where no task follows ("forgot RMSE", "forgot PCC")
            heading = f"{name} {s.label}" if i == 0 or not when else s.label
            headers.append(f"{heading} {when}".rstrip())
    rows = []
    for r in results:
        after = r.after_tasks[0] | r.after_tasks[1]  # after_task1/..., after_task2/...
        rows.append(
            [label(r)]
            + [after[f"{prefix}/{s.name}"] for _, prefix, _ in FORGETTING_GROUPS for s in scores]
        )
    return table(headers, rows)
