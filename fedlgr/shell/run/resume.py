"""Picking a run up again (``fedlgr run --resume``): which run, its newest checkpoint, and whether
it belongs to this config and data; before the runtime is built (it adopts the run's settings)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fedlgr.errors import FedlgrError
from fedlgr.shell.config import ExperimentConfig, flatten
from fedlgr.shell.config.export import MACHINE_CHOSEN, SAFE_KEYS, config_hash
from fedlgr.shell.run import checkpoint as ckpt
from fedlgr.shell.run import owner
from fedlgr.shell.run.life import Resumed
from fedlgr.shell.tracking.context import data_digest
from fedlgr.shell.tracking.liveness import dead_reason
from fedlgr.shell.tracking.mlflow_run import experiment_id, open_client, tracking_uri


def resume_point(
    fabric, config: ExperimentConfig, resume: str | bool | None, adopt: frozenset[str] = frozenset()
) -> Resumed | None:
    """The run ``resume`` names (its id, or True: the latest unfinished run of this config) and its
    checkpoint, or None without ``resume``. Rank 0 finds it, every process reads it."""
    if not resume:
        return None
    _needs_tracking(config)
    found: tuple[str, str] | str = ""
    if fabric is None or fabric.global_rank == 0:
        try:
            run_id, path = find_checkpoint(config, resume, open_client(tracking_uri(config)))
            found = (run_id, str(path))
        except FedlgrError as err:
            found = str(err)
    if fabric is not None and fabric.world_size > 1:
        found = fabric.broadcast(found, src=0)
    if isinstance(found, str):
        raise FedlgrError(found)
    run_id, path = found
    try:
        state = load_checkpoint(config, run_id, Path(path), adopt)
    except BaseException:
        owner.release(Path(path).parent)  # claimed by find_checkpoint (rank 0)
        raise
    return Resumed(run_id, state, Path(path).parent)


def check_resumable(config: ExperimentConfig, resume: str | bool) -> None:
    """Refuse a resume that :func:`resume_point` would refuse for want of a run to resume - none
    unfinished, or the one named has finished - reading the store only (nothing claimed, marked
    or removed): ``fedlgr deploy run`` says so before a Flower run starts."""
    _needs_tracking(config)
    info = _the_run(config, resume, open_client(tracking_uri(config))).info
    if info.status == "FINISHED":
        raise FedlgrError(f"--resume: run {info.run_id} has finished; there is nothing to resume")


def _needs_tracking(config: ExperimentConfig) -> None:
    if not config.tracking.enabled:
        raise FedlgrError("--resume needs tracking.enabled=true (runs are found in MLflow)")


def left_to_machine(config: ExperimentConfig) -> frozenset[str]:
    """The machine-chosen settings (:data:`MACHINE_CHOSEN`) this launch leaves unset: a
    resumed run takes its own values for them instead."""
    rt = config.runtime
    left = {"runtime.threads": rt.threads, "runtime.workers": rt.workers}
    left["runtime.concurrency"] = None if rt.concurrency == "auto" else "set"
    return frozenset(k for k in MACHINE_CHOSEN if left[k] is None)


def find_checkpoint(config: ExperimentConfig, resume: str | bool, client) -> tuple[str, Path]:
    """The run to resume (``resume``: its id, or True for the latest unfinished run of this config)
    and its newest checkpoint; dead RUNNING runs are marked KILLED, a live one is refused."""
    run = _the_run(config, resume, client)
    run_id, folder = run.info.run_id, checkpoint_folder(run, config)
    for _ in range(3):  # a resume under way elsewhere may move the run's checkpoints meanwhile
        if folder.is_dir():
            break
        run = client.get_run(run_id)
        if (moved := checkpoint_folder(run, config)) == folder:
            break
        folder = moved
    if run.info.status == "FINISHED":
        raise FedlgrError(
            f"--resume: run {run_id} has finished; there is nothing to resume"
            + remove_leftover(folder, run_id)
        )
    if not ckpt.checkpoints(folder):
        if folder.is_dir():  # e.g. the folder a live owner moved its checkpoints to
            owner.claim(folder, run_id)  # refused, naming that owner
            owner.release(folder)
        raise FedlgrError(
            f"--resume: run {run_id} has no checkpoint in {folder} (it stopped before its first "
            "checkpoint, or tracking.checkpoint=0); start it over without --resume"
        )
    owner.claim(folder, run_id)  # from here on no other process can resume it too
    try:  # now that we own it, its owner has ended: a RUNNING run is dead, and marked KILLED
        run = client.get_run(run_id)
        if run.info.status == "FINISHED":
            raise FedlgrError(f"--resume: run {run_id} has finished; there is nothing to resume")
        if run.info.status == "RUNNING":
            reason = dead_reason(run)
            if reason is None:
                tags = run.data.tags
                raise FedlgrError(
                    f"--resume: run {run_id} is still running (process "
                    f"{tags.get('fedlgr.pid')} on {tags.get('fedlgr.host')}); stop it first, "
                    "or wait until it ends"
                )
            client.set_tag(run_id, "fedlgr.ended", f"marked KILLED: {reason}")
            client.set_terminated(run_id, "KILLED")
        found = ckpt.checkpoints(folder)
        if not found:
            raise FedlgrError(f"--resume: run {run_id}'s checkpoints in {folder} are gone")
    except BaseException:
        owner.release(folder)
        raise
    return run_id, found[-1]


def remove_leftover(folder: Path, run_id: str) -> str:
    """Remove the checkpoint folder a finished run left behind (killed between its end and
    the folder's removal); what was done, as a clause for a message ("" if nothing)."""
    if not folder.is_dir():
        return ""
    try:
        owner.claim(folder, run_id)  # an owner still finishing it removes the folder itself
    except FedlgrError:
        return ""
    size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
    owner.release(folder)
    ckpt.remove(folder)
    return f" (removed the checkpoint folder it left behind, {folder}: {size / 2**20:.0f} MiB)"


def checkpoint_folder(run, config: ExperimentConfig) -> Path:
    """Where ``run`` keeps its checkpoints: where this config puts them if they are there (a store
    moved with its checkpoints, a folder named on the command line), else the run's tag."""
    here = ckpt.checkpoint_root(config, tracking_uri(config)) / run.info.run_id
    tagged = run.data.tags.get("fedlgr.checkpoints")
    if not tagged or ckpt.checkpoints(here):
        return here
    return Path(tagged)


def _the_run(config: ExperimentConfig, resume: str | bool, client):
    """The MLflow run ``resume`` names: its id, or True for the latest unfinished run."""
    if resume is not True:
        try:
            return client.get_run(str(resume))
        except Exception:
            uri = tracking_uri(config)
            raise FedlgrError(f"--resume {resume}: no such run in the MLflow store {uri}") from None
    experiment = experiment_id(client, config.tracking.experiment)
    ours = f"tags.`fedlgr.config_hash` = '{config_hash(config)}'"
    newest_first = ["attributes.start_time DESC"]
    query = f"{ours} and attributes.status != 'FINISHED'"
    runs = client.search_runs([experiment], query, order_by=newest_first)
    if not runs:
        # named, so that two launches resuming at once are told which run the other finished
        finished = client.search_runs([experiment], ours, order_by=newest_first, max_results=1)
        newest = f" (run {finished[0].info.run_id} has finished)" if finished else ""
        raise FedlgrError(
            f"--resume: no unfinished run of this config in MLflow experiment "
            f"{config.tracking.experiment!r}{newest}; give a run id (--resume RUN_ID), or "
            "start the run without --resume"
        )
    return runs[0]


def load_checkpoint(
    config: ExperimentConfig, run_id: str, path: Path, adopt: frozenset[str] = frozenset()
) -> dict[str, Any]:
    """The checkpoint at ``path`` if it belongs to ``run_id`` and ``config``; settings in ``adopt``
    (left to the machine by this launch) are not compared: the run's own are taken."""
    state = ckpt.load(path, ckpt.RUN_KEYS)
    if state["run_id"] != run_id:
        raise FedlgrError(f"{path}: a checkpoint of run {state['run_id']}, not of run {run_id}")
    saved = {k: v for k, v in state["config"].items() if k not in adopt}
    current = {k: v for k, v in flatten(config).items() if k not in adopt}
    changed = [  # every setting that differs, safe keys aside
        f"{k} (checkpoint {saved.get(k, 'unset')}, now {current.get(k, 'unset')})"
        for k in sorted((saved.keys() | current.keys()) - SAFE_KEYS)
        if saved.get(k) != current.get(k)
    ]
    if changed:
        more = f"; and {len(changed) - 5} more" if len(changed) > 5 else ""
        shown = "; ".join(changed[:5]) + more
        raise FedlgrError(
            f"--resume: the config differs from run {run_id}'s checkpoint in {shown}; resume "
            "with the run's own settings, or start a new run without --resume"
        )
    saved_digest = state.get("data_digest", "")  # "" in checkpoints of older fedlgr
    if saved_digest and (now := data_digest(config)) != saved_digest:
        raise FedlgrError(
            f"--resume: the data in data.path={config.data.path} is not the data run {run_id} "
            f"trained on (dataset digest {now}, the checkpoint's {saved_digest}); resume on "
            "the run's own data, or start a new run without --resume"
        )
    return {**state, "path": str(path)}


def adopted(resumed: Resumed | None, keys: frozenset[str]) -> dict[str, Any]:
    """A resumed run's own values of the machine-chosen settings ``keys`` (its
    checkpoint's flattened config), by name: ``{"threads": 2, "concurrency": ...}``."""
    saved = resumed.state["config"] if resumed is not None else {}
    found = {
        k.removeprefix("runtime."): saved[k] for k in keys if saved.get(k) not in (None, "None")
    }
    return {k: int(v) if k in ("threads", "workers") else v for k, v in found.items()}
