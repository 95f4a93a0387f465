"""Bad settings and bad data refused in one line before anything is allocated (issue 20,
points 8 and 9): seeds, non-finite floats, floats for integers, sizes that cannot fit,
MLflow's name limit, thread intervals, rounds, a report folder that is a file, two scenes
under one stamp, degenerate images, and a task schedule some client holds no scenes of
(issue 40)."""

from __future__ import annotations

import re
import threading

import mlflow.utils.validation
import pytest
from PIL import Image

import fedlgr.shell.checks.experiment as experiment_checks
import fedlgr.shell.config as config_module
import fedlgr.shell.data.dataset as dataset_module
import fedlgr.shell.data.images as images_module
import fedlgr.shell.report.runs as report_runs
from fedlgr.errors import ConfigError, DataError
from fedlgr.shell.cli import main
from fedlgr.shell.config import DataConfig, FederatedConfig, ModelConfig, load_config
from fedlgr.shell.data.dataset import load_scenes
from fedlgr.shell.data.ratings import read_ratings
from fedlgr.shell.data.splits import make_split, task_clients
from tests.support.data import HEADER, rating_row, write_rows
from tests.support.runs import FAST


def refused(overrides: list[str], error=ConfigError) -> str:
    """The one-line message with which ``load_config`` refuses ``overrides``."""
    with pytest.raises(error) as caught:
        load_config(None, overrides)
    message = str(caught.value)
    assert "\n" not in message
    return message


# --------------------------------------------------------------------------- settings


@pytest.mark.parametrize("override", ["seed=-1", "seed=4294967296", "data.seed=-1"])
def test_seeds_outside_32_bits_are_refused(override):
    message = refused([override])
    assert message.startswith(override + ":")
    assert "0..4294967295" in message and "32-bit" in message


def test_the_largest_32_bit_seed_is_accepted():
    assert load_config(None, ["seed=4294967295", "data.seed=4294967295"]).seed == 2**32 - 1


@pytest.mark.parametrize(
    ("override", "shown"),
    [
        ("federated.opt.lr=inf", "federated.opt.lr=inf"),
        ("federated.opt.tau=nan", "federated.opt.tau=nan"),
        ("train.lr_root=-inf", "train.lr_root=-inf"),
        ("train.betas=[0.9,.nan]", "train.betas=[0.9, nan]"),
        ("model.width=nan", "model.width=nan"),
        ("continual.ewc.lambda_=.inf", "continual.ewc.lambda_=inf"),
        ("deploy.join_timeout_s=.inf", "deploy.join_timeout_s=inf"),
        ("data.dirichlet_alpha=inf", "data.dirichlet_alpha=inf"),
    ],
)
def test_nan_and_infinite_floats_are_refused_in_every_section(override, shown):
    assert refused([override]) == f"{shown}: must be a finite number"


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: ModelConfig(mlp_hidden=(1e9,)), "model.mlp_hidden=[1000000000.0]"),
        (lambda: DataConfig(augment_copies=1e9), "data.augment_copies=1000000000.0"),
        (lambda: FederatedConfig(rounds=10.0), "federated.rounds=10.0"),
    ],
)
def test_floats_where_integers_are_expected_are_refused(build, message):
    # load_config refuses them through OmegaConf's types; code building the dataclasses
    # directly gets the same check
    with pytest.raises(
        ConfigError, match=rf"^{re.escape(message)}: must be an integer, not a float$"
    ):
        build()


def test_a_model_too_large_for_the_memory_is_refused_with_the_estimate(monkeypatch):
    monkeypatch.setattr(experiment_checks, "machine_memory", lambda: 64 * 10**9, raising=False)
    message = refused(["data.modality=features", "model.mlp_hidden=[1000000000]"])
    # Linear(29, 1e9) + BatchNorm(1e9) + the top's BatchNorm(1e9) and Linear(1e9, 32):
    # ~7e10 numbers x 16 bytes
    assert message.startswith("model.mlp_hidden=[1000000000] with model.top_hidden=32:")
    assert "~7e+10 parameters" in message and "1.1 TB to train" in message
    assert "64.0 GB of memory (psutil.virtual_memory().total)" in message
    assert "model.top_hidden=1000000000" in refused(["model.top_hidden=1000000000"])
    load_config(None, ["data.modality=features"])  # the default MLP fits


def test_image_size_and_augment_copies_are_bounded_with_the_estimate():
    message = refused(["data.image_size=100000"])
    assert message.startswith("data.image_size=100000: at most 4096 (a fixed bound")
    assert "30.0 GB and 120.0 GB here" in message  # 3 and 12 bytes x 100000^2
    message = refused(["data.augment_copies=1000000000"])
    assert message.startswith("data.augment_copies=1000000000: at most 1000 (a fixed bound")
    assert "24.0 GB per scene" in message
    load_config(None, ["data.image_size=4096", "data.augment_copies=1000"])


def test_rounds_are_bounded():
    message = refused(["federated.rounds=1000000000"])
    assert message.startswith("federated.rounds=1000000000: at most 1000000 rounds")
    message = refused(["continual.tasks=[circle,arrow]", "continual.rounds_per_task=600000"])
    assert message.startswith("continual.rounds_per_task=600000 x 2 tasks = 1200000 rounds:")
    assert refused(["continual.rounds_per_task=1000001"]).startswith(
        "continual.rounds_per_task=1000001: at most 1000000 rounds"
    )


def test_an_experiment_name_over_mlflows_limit_is_refused():
    assert config_module.MAX_EXPERIMENT_NAME == mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH
    message = refused(["tracking.experiment=" + "x" * 501])
    assert message == (
        "tracking.experiment: 501 characters, MLflow allows at most 500 "
        "(mlflow.utils.validation.MAX_EXPERIMENT_NAME_LENGTH)"
    )
    load_config(None, ["tracking.experiment=" + "x" * 500])


@pytest.mark.parametrize("name", ["heartbeat_s", "system_metrics_s"])
@pytest.mark.parametrize("value", ["1e300", "86401", "0", "0.0001"])
def test_thread_intervals_must_be_a_second_to_a_day(name, value):
    # threading.Event.wait raises OverflowError above TIMEOUT_MAX, killing the thread;
    # 0.0001 s was taken (the seventh fault sweep, z10/z13)
    assert config_module.MAX_INTERVAL_S <= threading.TIMEOUT_MAX
    message = refused([f"tracking.{name}={value}"])
    assert message.startswith(f"tracking.{name}=")
    assert "from 1 to 86400 seconds" in message
    load_config(None, [f"tracking.{name}=1"])


@pytest.mark.parametrize("value", ["0.001", "0", "604801"])
def test_the_multi_process_timeout_is_a_second_to_a_week(value):
    assert refused([f"runtime.timeout_s={value}"]) == (
        f"runtime.timeout_s={float(value)}: from 1 second to a week (604800)"
    )


def test_a_report_folder_that_is_a_file_is_one_line(tmp_path, monkeypatch, capsys):
    # no store is needed to reach the folder: the runs are stood in for
    selection = report_runs.Selection(
        client=None,
        uri="sqlite:///x",
        name="exp",
        source="experiment `exp`",
        experiment_ids=[],
        sweep=None,
        records=[],
    )
    monkeypatch.setattr(report_runs, "open_store", lambda uri: None)
    monkeypatch.setattr(report_runs, "select_runs", lambda *a, **k: selection)
    file = tmp_path / "report.md"
    file.write_text("not a folder")
    uri = ["--tracking-uri", "sqlite:///x", "--no-log"]
    for out, why in ((file, "is a file"), (file / "sub", f"lies under {file}, a file")):
        assert main(["report", "--out", str(out), *uri]) == 1
        err = capsys.readouterr().err
        assert err == f"fedlgr: error: {out}: {why}; the report (--out) is a folder of " + (
            "tables and plots: name a new or existing folder\n"
        )
    monkeypatch.chdir(tmp_path)  # the default folder, reports/exp, is a file too
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "exp").write_text("")
    assert main(["report", *uri]) == 1
    assert "reports/exp: is a file" in capsys.readouterr().err


# --------------------------------------------------------------------------- data


def _dataset(folder, rows, sizes=None):
    write_rows(folder / "all_data.csv", [HEADER, *rows])
    for stamp, size in (sizes or {}).items():
        (folder / "images").mkdir(parents=True, exist_ok=True)
        Image.new("RGB", size, (90, 120, 200)).save(folder / "images" / f"{stamp}.png")
    return folder


def test_two_scenes_under_one_stamp_are_refused(tmp_path):
    labels = [3, 3, 3, 3, 3, 3, 3, 3]
    folder = _dataset(
        tmp_path,
        [
            rating_row(250, True, labels, descriptor=0.5),
            rating_row(251, True, labels, descriptor=0.5),
            rating_row(250, True, [4] * 8, descriptor=0.7),  # another scene's descriptors
            rating_row(251, True, [4] * 8, descriptor=0.5),  # another rater: averaged
        ],
    )
    with pytest.raises(DataError) as caught:
        read_ratings(folder)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{folder / 'all_data.csv'}: stamp 250, columns 'Number of people'")
    assert "and 26 more: its rows [1, 3] disagree" in message
    assert "descriptors must be the same in all its rows" in message
    assert "251" not in message.split("(")[0]


def test_a_degenerate_image_is_refused_and_can_be_skipped(tmp_path, cache_dir):
    rows = [rating_row(s, True, [3] * 8) for s in (250, 251, 252)]
    folder = _dataset(tmp_path / "data", rows, {250: (32, 32), 251: (1, 1), 252: (32, 7)})
    with pytest.raises(DataError) as caught:
        load_scenes(DataConfig(path=folder, image_size=16, cache=False))
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{folder / 'images' / '251.png'}: 1x1 pixels, under the 8 px")
    assert "resized to data.image_size=16" in message
    config = DataConfig(path=folder, image_size=16, cache=False, on_bad_image="skip")
    with pytest.warns(UserWarning) as warned:
        scenes = load_scenes(config)
    assert scenes.stamps.tolist() == [250]
    skipped = sorted(str(w.message).split(": ", 1)[0] for w in warned)
    assert skipped == ["skipping stamp 251", "skipping stamp 252"]
    assert "252.png: 32x7 pixels" in str(warned[-1].message) + str(warned[0].message)


def test_an_image_store_larger_than_the_memory_is_refused_before_decoding(tmp_path, monkeypatch):
    rows = [rating_row(s, True, [3] * 8) for s in (250, 251)]
    folder = _dataset(tmp_path / "data", rows, {250: (32, 32), 251: (32, 32)})
    monkeypatch.setattr(images_module, "machine_memory", lambda: 700_000, raising=False)

    def never(*args):
        raise AssertionError("decoded although the store cannot fit")

    monkeypatch.setattr(images_module, "decode", never)
    with pytest.raises(ConfigError) as caught:
        load_scenes(DataConfig(path=folder, image_size=256, cache=False))
    assert str(caught.value) == (
        "data.image_size=256: the decoded images of 2 scenes take 393.2 kB (2 x 3 x 256^2 "
        "bytes) and twice that while they are stacked, more than this machine's 700.0 kB of "
        "memory (psutil.virtual_memory().total)"
    )


@pytest.mark.slow
def test_a_schedule_some_client_cannot_train_is_refused_before_any_image_is_decoded(
    tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """FCL trains every client on each scheduled task in turn: 20 clients on the 36
    training scenes leave some without one. The split is refused in one line from
    all_data.csv - no image decoded, no MLflow run - with how many clients lack each task
    and the most clients that give every client both (they do; one more does not)."""

    def never(*args, **kwargs):
        raise AssertionError("images decoded before the split was checked")

    monkeypatch.setattr(dataset_module, "load_image_store", never)
    monkeypatch.setattr(images_module, "decode", never)
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    argv = ["run", str(FAST), f"data.path={synth_dir}", f"data.cache_dir={cache_dir}"]
    assert main([*argv, "--tracking-uri", store, "method=FedAvg-EWC", "data.clients=20"]) == 1
    err = capsys.readouterr().err.strip()

    # What it must say, from plain splits (which allow a client without a task).
    table = read_ratings(synth_dir)
    both = ("circle", "arrow")

    def held(clients: int) -> dict[str, int]:
        return task_clients(make_split(table, DataConfig(clients=clients)))

    lacking = sorted(((20 - k, t) for t, k in held(20).items()), key=lambda kt: -kt[0])
    assert all(k > 0 for k, _ in lacking)
    most = max(k for k in range(1, 20) if held(k) == {"circle": k, "arrow": k})
    assert 1 < most < 19
    assert err == (
        f"fedlgr: error: data.clients=20: {lacking[0][0]} clients hold no training scenes of "
        f"task {lacking[0][1]!r} and {lacking[1][0]} none of {lacking[1][1]!r} (continual.tasks "
        "needs every client to hold each task it trains); "
        f"data.clients={most} is the most that give every client scenes of every task with "
        "data.seed=0, or use fewer continual.tasks / plain FL"
    )
    split = make_split(table, DataConfig(clients=most), both)
    assert all(len(c.tasks[t]) for c in split.clients for t in both)
    with pytest.raises(ConfigError, match=f"^data.clients={most + 1}: "):
        make_split(table, DataConfig(clients=most + 1), both)
    assert not cache_dir.exists()
    client = mlflow.MlflowClient(store)
    assert not client.search_runs([e.experiment_id for e in client.search_experiments()])


def test_an_empty_config_file_is_refused(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(ConfigError, match=r"empty.yaml: holds no settings \(an empty file\)"):
        load_config(empty)


def test_machine_settings_no_machine_has_are_refused_in_one_line(tmp_path, capsys):
    """Found by the fault sweep: tracebacks at runtime.threads=1000000 (1004 MemoryErrors)
    and runtime.accelerator=gpu on a machine without one; a sweep's --workers 100000 started
    processes until SIGTERM, --workers 0 ran one; a folder given as the config, and an
    empty --tracking-uri (it fell back to the default store)."""
    import torch

    from fedlgr.shell.config import SWEEPS_DIR

    fast, sweep = str(FAST), str(SWEEPS_DIR / "fedlgr.yaml")
    assert "runtime.threads=1000000: at most 1024" in refused(["runtime.threads=1000000"])
    assert "runtime.devices=5000: at most 1024" in refused(["runtime.devices=5000"])
    cases = [
        (["run", str(tmp_path)], f"{tmp_path}: a folder, not a config file"),
        (["run", fast, "--tracking-uri", ""], "--tracking-uri '': empty"),
        (["sweep", sweep, "--workers", "0"], "--workers 0: from 1 to"),
        (["sweep", sweep, "--workers", "100000"], "--workers 100000: from 1 to"),
        (["sweep", sweep, "--heartbeat", str(10**12)], f"--heartbeat {10**12}: from 1 to 86400"),
    ]
    if not torch.cuda.is_available():
        cases.append(
            (
                # a data.path that exists: a missing one is refused first, before torch loads
                ["run", fast, f"data.path={tmp_path}", "runtime.accelerator=gpu"],
                "runtime.accelerator=gpu: no CUDA GPU on this machine",
            )
        )
    for argv, said in cases:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and said in err, (argv, err)


@pytest.mark.slow
def test_found_by_the_third_sweep_are_one_line_before_any_work(
    tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """A checkpoint folder that is a file, or lies under one (a read-only mount took the
    same path: a traceback from the owner's lock and a FAILED run), is refused before the
    MLflow run exists; `fedlgr data synth --size 100000` drew for minutes and ignored
    SIGTERM; `fedlgr report --out ''` filled the current folder with the report."""
    store = tmp_path / "mlflow.db"
    afile = tmp_path / "ckfile"
    afile.write_text("x")
    base = ["run", str(FAST), f"data.path={synth_dir}", "--tracking-uri", f"sqlite:///{store}"]
    assert main([*base, f"tracking.checkpoint_dir={afile}"]) == 1
    said = f"fedlgr: error: tracking.checkpoint_dir={afile}: a file, not a folder"
    assert capsys.readouterr().err.strip() == said
    assert main([*base, f"tracking.checkpoint_dir={afile / 'sub'}"]) == 1
    said = (
        f"fedlgr: error: tracking.checkpoint_dir={afile / 'sub'}: under {afile}, a file, "
        "not a folder"
    )
    assert capsys.readouterr().err.strip() == said
    client = mlflow.MlflowClient(f"sqlite:///{store}")
    assert not client.search_runs([e.experiment_id for e in client.search_experiments()])

    assert main(["data", "synth", "--out", str(tmp_path / "s"), "--size", "100000"]) == 1
    assert "size=100000: images are 16 to 4096 pixels wide" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()

    monkeypatch.chdir(tmp_path)
    before = sorted(tmp_path.iterdir())
    for out in ("", "."):
        assert main(["report", "--out", out, "--tracking-uri", f"sqlite:///{store}"]) == 1
        err = capsys.readouterr().err.strip()
        assert err == (
            "fedlgr: error: --out names the current folder ('' or .): name a folder of its "
            "own for the report's tables and plots (default: reports/NAME)"
        )
    assert sorted(tmp_path.iterdir()) == before


def test_synthetic_data_goes_to_a_folder_of_its_own_that_can_be_written(
    tmp_path, capsys, monkeypatch
):
    """Found by the re-test: `data synth` to a read-only place was a traceback, and
    `--out ''` wrote the dataset into the current folder."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["data", "synth", "--out", str(afile / "s"), "--scenes", "1", "--size", "16"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"fedlgr: error: {afile / 's'}: under {afile}, a file, not a folder"
    monkeypatch.chdir(tmp_path)
    for out in ("", "."):
        assert main(["data", "synth", "--out", out, "--scenes", "1", "--size", "16"]) == 1
        assert "--out names the current folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
