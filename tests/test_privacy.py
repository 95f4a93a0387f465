"""Client-level differential privacy (``federated.dp.*``, :mod:`fedlgr.core.privacy`):
clipping and noise on hand numbers, the noise drawn again for a seed, adaptive clipping's
step, the accountant against dp-accounting's for the same noise, sampling and rounds, and
runs that log epsilon and stop at a target. Adaptive clipping's count of centred bits and
the epsilon of the mechanism that runs were checked against independent reference code
in the methods review of issue 48."""

from __future__ import annotations

import functools
import math

import dp_accounting
import mlflow
import pytest
import torch
from dp_accounting import rdp

from fedlgr.core import privacy
from fedlgr.core.messages import TrainRes
from fedlgr.core.privacy import UNCLIPPED, Privacy
from fedlgr.core.schedule import schedule
from fedlgr.core.server.side import ServerSide
from fedlgr.core.strategies.base import participants
from fedlgr.errors import ConfigError, FedlgrError
from fedlgr.shell.cli import main
from fedlgr.shell.config import load_config
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config, results_csv


def dp_config(*overrides):
    return load_config(None, ["data.clients=4", "federated.dp.delta=0.01", *overrides])


def test_clip_scales_the_whole_update_as_one_vector_by_hand():
    """(3, 4) and (12,) make one vector of norm 13: clipped to 6.5 it halves; a bound over
    its norm leaves it as it is."""
    update = {"a": torch.tensor([3.0, 4.0]), "b": torch.tensor([12.0])}
    clipped, size = privacy.clip(update, 6.5)
    assert size == 13.0
    assert clipped["a"].tolist() == [1.5, 2.0] and clipped["b"].tolist() == [6.0]
    same, _ = privacy.clip(update, 13.0)
    assert same["a"].tolist() == [3.0, 4.0] and same["b"].tolist() == [12.0]


def test_an_upload_is_clipped_around_the_global_tensors_with_its_payload_and_weighs_one():
    """g = (1, 1), w = (4, 5): update (3, 4), payload (0,) + (12,): norm 13 over clip 2.6
    -> scaled by 0.2: w' = (1.6, 1.8), payload 2.4; it was not within the clip norm: its
    centred bit is 0 - 1/2 (1 - 1/2 for one within)."""
    config = dp_config("federated.dp.clip=2.6")
    server = Privacy(config)
    shared = {"w": torch.tensor([1.0, 1.0])}
    res = TrainRes(0, {"w": torch.tensor([4.0, 5.0])}, 37, payload={"c": torch.tensor([12.0])})
    out = server.clipped(res, shared)
    assert out.n_samples == 1
    assert out.weights["w"].tolist() == pytest.approx([1.6, 1.8])
    assert out.payload["c"].tolist() == pytest.approx([2.4])
    assert out.payload[UNCLIPPED].item() == -0.5
    small = TrainRes(0, {"w": torch.tensor([1.5, 1.0])}, 3)
    assert server.clipped(small, shared).payload[UNCLIPPED].item() == 0.5


def test_the_release_is_the_global_plus_the_noisy_sum_over_q_n_by_hand():
    """Without noise: g = 1, two clipped uploads 2 and 4 (updates 1 and 3) of N = 4 clients
    at fraction 1 -> g + (1 + 3) / 4 = 2. With noise z = 0.5 and C = 2 the release moves
    by exactly the seeded draw of std 1, over 4."""
    shared = {"w": torch.tensor([1.0])}
    sums = {"w": torch.tensor([6.0], dtype=torch.float64)}  # 2 + 4
    quiet = Privacy(dp_config("federated.dp.clip=2", "federated.dp.noise_multiplier=0"))
    mean, _ = quiet.mean(sums, 2.0, {}, shared)
    assert mean["w"].tolist() == [2.0]
    noisy = Privacy(dp_config("federated.dp.clip=2", "federated.dp.noise_multiplier=0.5"))
    mean, _ = noisy.mean(sums, 2.0, {}, shared)
    draw = privacy.generator(0, 1, privacy._NOISE_TAG, from_os=False)
    noise = torch.randn((1,), dtype=torch.float64, generator=draw) * 1.0
    assert mean["w"].item() == pytest.approx(2.0 + noise.item() / 4, abs=1e-7)
    assert noisy.releases == 1


def test_the_noise_has_the_stated_deviation_and_a_seed_draws_it_again():
    like = {"big": torch.zeros(200_000)}
    draw = privacy.generator(3, 1, privacy._NOISE_TAG, from_os=False)
    noise = privacy.gaussian(like, 0.7, draw)["big"]
    assert noise.std().item() == pytest.approx(0.7, rel=0.01)
    assert abs(noise.mean().item()) < 0.01
    again = privacy.gaussian(like, 0.7, privacy.generator(3, 1, privacy._NOISE_TAG, False))
    assert torch.equal(noise, again["big"])
    other = privacy.gaussian(like, 0.7, privacy.generator(3, 2, privacy._NOISE_TAG, False))
    assert not torch.equal(noise, other["big"])  # the next release, the next draw
    from_os = [privacy.gaussian(like, 0.7, privacy.generator(3, 1, 0, True)) for _ in range(2)]
    assert not torch.equal(from_os[0]["big"], from_os[1]["big"])  # deployment: the OS's


def test_adaptive_clipping_moves_the_clip_norm_towards_its_quantile_by_hand():
    """All 4 of 4 clients within C = 2 (centred bits: 4 x 1/2 = 2), target quantile 0.5,
    step 0.2: share 2 / 4 + 1/2 = 1, C <- 2 exp(-0.2 x 0.5) (count noise 1e-9: none to
    speak of); the updates' noise multiplier is raised so that both releases cost one
    Gaussian of z (Andrew et al., Th. 1: the count's multiplier is 2 sigma_b)."""
    config = dp_config(
        "federated.dp.clip=2",
        "federated.dp.noise_multiplier=0",
        "federated.dp.clipping=adaptive",
        "federated.dp.count_noise=1e-9",
    )
    server = Privacy(config)
    shared = {"w": torch.tensor([0.0])}
    server.mean({"w": torch.tensor([0.4], dtype=torch.float64)}, 4.0, {UNCLIPPED: 2.0}, shared)
    assert server.bound == pytest.approx(2 * math.exp(-0.1))
    assert privacy.update_multiplier(1.0, 1.0) == pytest.approx((1 - 0.25) ** -0.5)
    with pytest.raises(ValueError, match="over noise_multiplier / 2"):
        privacy.update_multiplier(1.0, 0.5)


ADAPTIVE = ["federated.dp.clip=1", "federated.dp.clipping=adaptive", "federated.dp.count_noise=1"]


def upload(server: ServerSide, client: int, size: float) -> TrainRes:
    """An upload whose update is ``size`` in L2: the global tensors with ``size`` added to
    one value."""
    weights = {k: g.clone().contiguous() for k, g in server.global_weights.items()}
    first = next(iter(weights))
    weights[first].view(-1)[0] += size
    return TrainRes(client, weights, 10)


def released_count(sizes: list[float]) -> float:
    """The count adaptive clipping releases in round 1 (seed 0) when clients of updates
    ``sizes`` upload, through the server's own path: screening, clipping, the sum of the
    centred bits, the noise (``Privacy.count``)."""
    server = ServerSide(dp_config(*ADAPTIVE, "data.modality=features"))  # a small model
    server.aggregate([upload(server, c, size) for c, size in enumerate(sizes)])
    return server.privacy.count


def step_of(a: float, b: float, step: float) -> bool:
    """Is ``b - a`` the count's ``step``? The bits' sums are exact (halves); each count is
    one rounding of sum + noise and the difference one more: off by at most 2^-53 (|a| +
    |b|) + 2^-53 |b - a|, which 2^-52 (|a| + |b| + 1) covers."""
    return abs((b - a) - step) <= 2.0**-52 * (abs(a) + abs(b) + 1)


@functools.cache
def measured_sensitivity() -> float:
    """What one client adds to the released count, measured on the server's path (a
    client within the clip norm added to a round of none): ``COUNT_SENSITIVITY``."""
    assert step_of(released_count([]), released_count([0.5]), privacy.COUNT_SENSITIVITY)
    return privacy.COUNT_SENSITIVITY


@pytest.mark.parametrize("others", [[], [0.5, 3.0, 0.25]], ids=["alone", "with-others"])
def test_one_client_moves_the_released_count_of_adaptive_clipping_by_exactly_one_half(others):
    """Neighbouring datasets, one client added (within the clip norm 1, or over it): the
    released counts, with the same seeded noise, differ by +1/2 or -1/2 - the sensitivity
    Andrew et al.'s Theorem 1 (the updates' noise z_u) assumes. With 0/1 bits it was 1."""
    count = released_count(others)
    within = released_count([*others, 0.5])
    over = released_count([*others, 3.0])
    assert step_of(count, within, 0.5) and step_of(count, over, -0.5)


# N, q, z, sigma_b (0: the default q N / 20), rounds, delta; the reported epsilon (of z)
# and the epsilon of what ran before the bits were centred (0/1 bits), both to 2 decimals
TABLE = [
    (100, 0.5, 1.0, 0.0, 20, 1e-3, 12.67, 13.85),
    (1000, 0.1, 1.0, 5.0, 100, 1e-4, 6.82, 7.01),
    (40, 0.25, 1.0, 0.6, 20, 1e-3, 6.48, 19.34),
    (200, 0.2, 0.8, 2.0, 50, 1e-4, 14.85, 16.53),
]


def single_gaussian_epsilon(multiplier: float, rate: float, releases: int, delta: float) -> float:
    """dp-accounting's RDP epsilon of ``releases`` Poisson-sampled Gaussians, asked directly."""
    event = dp_accounting.SelfComposedDpEvent(
        dp_accounting.PoissonSampledDpEvent(rate, dp_accounting.GaussianDpEvent(multiplier)),
        releases,
    )
    return rdp.RdpAccountant().compose(event).get_epsilon(delta)


def mechanism_multiplier(server: Privacy, sensitivity: float) -> float:
    """The one Gaussian a round of adaptive clipping is: the updates' multiplier z_u (norm
    C, noise z_u C) beside the count's sigma_b / s, for a count of sensitivity ``s``."""
    return (server.multiplier**-2 + (server.count_std / sensitivity) ** -2) ** -0.5


@pytest.mark.parametrize(("n", "q", "z", "sigma_b", "rounds", "delta", "reported", "old"), TABLE)
def test_adaptive_clippings_epsilon_is_the_mechanisms_on_issue_48s_table(
    n, q, z, sigma_b, rounds, delta, reported, old
):
    """fedlgr's updates' multiplier z_u (``update_multiplier``) with the count's noise at
    the sensitivity measured on the server's path (1/2) make one Gaussian of multiplier
    z, so the epsilon fedlgr reports is
    dp-accounting's for the mechanism (to 1e-3, issue 48's acceptance); with the old 0/1
    bits (sensitivity 1) the mechanism cost the right-hand column."""
    config = load_config(
        None,
        [
            f"data.clients={n}",
            f"federated.fraction={q}",
            "federated.dp.clip=1",
            "federated.dp.clipping=adaptive",
            f"federated.dp.noise_multiplier={z}",
            f"federated.dp.count_noise={sigma_b}",
            f"federated.dp.delta={delta}",
        ],
    )
    server = Privacy(config)
    assert server.count_std == (sigma_b or q * n / 20)
    assert server.multiplier == privacy.update_multiplier(z, server.count_std)
    running = mechanism_multiplier(server, measured_sensitivity())
    # z_u^-2 = z^-2 - (2 sigma_b)^-2 then back: about 8 roundings of 2^-53, the subtraction
    # amplifying them by at most z^-2 / z_u^-2
    amplified = z**-2 / server.multiplier**-2
    assert abs(running - z) <= 16 * amplified * 2.0**-53 * z
    server.load_state_dict({"bound": 1.0, "releases": rounds, "bits": "centred"})
    mechanism = single_gaussian_epsilon(running, q, rounds, delta)
    assert abs(server.epsilon - mechanism) <= 1e-3
    assert abs(server.epsilon - reported) <= 0.005  # the table's last digit
    before = privacy.epsilon(mechanism_multiplier(server, 1.0), q, rounds, delta)
    assert abs(before - old) <= 0.005 and before > server.epsilon


@pytest.mark.slow
def test_an_adaptive_runs_target_epsilon_stops_where_the_accountant_puts_the_mechanism(
    synth_dir, cache_dir
):
    """4 clients at fraction 0.5, z = 2, count noise 1.5: the run stops after the rounds
    whose epsilon of the mechanism (z_u with the count at the sensitivity measured on the
    server's path, asked of dp-accounting directly) fit the target, and reports that
    epsilon every round."""
    z, rate, delta = 2.0, 0.5, 0.01
    server = Privacy(
        dp_config(
            *ADAPTIVE,
            f"federated.dp.noise_multiplier={z}",
            "federated.dp.count_noise=1.5",
            "federated.fraction=0.5",
        )
    )
    running = mechanism_multiplier(server, measured_sensitivity())
    spent = [single_gaussian_epsilon(running, rate, r, delta) for r in range(1, 7)]
    target = (spent[2] + spent[3]) / 2  # three rounds fit, not four
    config = fast_config(
        synth_dir,
        cache_dir,
        "sqlite://",
        "tracking.enabled=false",
        "data.modality=features",  # the scenes' descriptors: the cheapest run
        "data.clients=4",
        "federated.rounds=6",
        f"federated.fraction={rate}",
        *ADAPTIVE,
        "federated.dp.count_noise=1.5",
        f"federated.dp.noise_multiplier={z}",
        f"federated.dp.delta={delta}",
        f"federated.dp.target_epsilon={target}",
    )
    assert len(schedule(config)) == 3
    result = run_experiment(config)
    assert [r.round for r in result.rounds] == [1, 2, 3]
    reported = [r.server["privacy/epsilon"] for r in result.rounds]
    assert all(abs(a - b) <= 1e-3 for a, b in zip(reported, spent[:3], strict=True))
    assert len({r.server["privacy/clip"] for r in result.rounds}) == 3  # the clip norm moved


def test_an_adaptive_checkpoint_of_0_1_bits_is_not_resumed():
    """Its releases cost more than the epsilon reported for them; fixed clipping's, and
    the centred bits', resume."""
    adaptive = Privacy(dp_config(*ADAPTIVE))
    with pytest.raises(FedlgrError, match="3 adaptive-clipping releases summed 0/1 bits"):
        adaptive.load_state_dict({"bound": 0.7, "releases": 3})
    adaptive.load_state_dict({"bound": 0.7, "releases": 0})  # nothing released yet
    adaptive.load_state_dict(Privacy(dp_config(*ADAPTIVE)).state_dict() | {"releases": 3})
    assert (adaptive.bound, adaptive.releases) == (1.0, 3)
    fixed = Privacy(dp_config("federated.dp.clip=1"))
    fixed.load_state_dict({"bound": 1.0, "releases": 3})
    assert fixed.releases == 3


@pytest.mark.parametrize(("rate", "z", "releases"), [(1.0, 1.1, 5), (0.3, 0.8, 12)])
def test_epsilon_is_dp_accountings_for_the_same_noise_sampling_and_rounds(rate, z, releases):
    event = dp_accounting.SelfComposedDpEvent(
        dp_accounting.PoissonSampledDpEvent(rate, dp_accounting.GaussianDpEvent(z)), releases
    )
    expected = rdp.RdpAccountant().compose(event).get_epsilon(1e-5)
    assert privacy.epsilon(z, rate, releases, 1e-5) == pytest.approx(expected, rel=1e-12)
    assert privacy.epsilon(z, rate, 0, 1e-5) == 0.0
    assert privacy.epsilon(0.0, rate, 1, 1e-5) == math.inf
    fits = privacy.releases_within(expected, z, rate, 1e-5, 100)
    assert fits == releases  # the most rounds whose epsilon stays within it


def test_clients_are_poisson_sampled_under_dp():
    """Each client on its own with probability q: the counts vary round to round (none
    at all in some), reproducibly for a seed; without DP exactly round(q N)."""
    counts = [len(participants(r, 10, 0.2, 0, poisson=True)) for r in range(1, 201)]
    assert counts == [len(participants(r, 10, 0.2, 0, poisson=True)) for r in range(1, 201)]
    assert 0 in counts and max(counts) >= 4
    assert sum(counts) / 2000 == pytest.approx(0.2, abs=0.03)
    assert {len(participants(r, 10, 0.2, 0)) for r in range(1, 50)} == {2}


def test_a_target_epsilon_cuts_the_schedule_before_the_round_that_would_exceed_it():
    spent = [privacy.epsilon(3.0, 1.0, r, 0.01) for r in range(1, 11)]
    target = (spent[2] + spent[3]) / 2  # three rounds fit, not four
    config = dp_config(
        "federated.rounds=10",
        "federated.dp.clip=1",
        "federated.dp.noise_multiplier=3",
        f"federated.dp.target_epsilon={target}",
    )
    steps = schedule(config)
    assert steps.planned == 10 and len(steps) == 3
    assert [plan.round for plan in steps] == [1, 2, 3]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["federated.strategy=median"],
            r"federated\.dp\.clip=1 with federated\.strategy=median: .*no such bound .*"
            r"use a mean-based strategy \(avg, bn, prox, opt, distill, avgm, scaffold\)$",
        ),
        (["federated.dp.delta=0.3"], r"federated\.dp\.delta=0\.3: must be below 1 / data\.clients"),
        (
            ["federated.dp.clipping=adaptive"],
            r"federated\.dp\.clipping=adaptive: the noise on the unclipped count \(0\.2 = ",
        ),
        (["federated.dp.quantile=1"], r"federated\.dp\.quantile=1\.0: must be in \(0, 1\)"),
        (
            ["federated.dp.noise_multiplier=0", "federated.dp.target_epsilon=3"],
            r"federated\.dp\.target_epsilon=3 needs noise",
        ),
    ],
)
def test_settings_dp_cannot_keep_are_refused_in_one_line(overrides, message):
    with pytest.raises(ConfigError, match=message):
        dp_config("federated.dp.clip=1", *overrides)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (  # was: the model ruined (RMSE 8524) while epsilon 1.08 was reported
            ["federated.dp.clip=1", "federated.fraction=0.25"],
            "federated.fraction=0.25 with data.clients=2: 0.5 expected clients a round under DP",
        ),
        (  # was: "stops after round 0", then an IndexError traceback
            ["federated.dp.clip=1", "federated.dp.target_epsilon=0.01"],
            "federated.dp.target_epsilon=0.01: round 1 alone spends epsilon 4.73 ",
        ),
        (  # was: dp-accounting's OverflowError
            ["federated.dp.clip=1", "federated.dp.noise_multiplier=1e300"],
            "federated.dp.noise_multiplier=1e+300: must be in 0..1000 (beyond it the noise",
        ),
        (  # was: ignored without a word
            ["federated.dp.target_epsilon=3"],
            "federated.dp.target_epsilon=3 with DP off (federated.dp.clip=0): there is no",
        ),
    ],
    ids=["fewer-than-one-client", "target-fits-no-round", "absurd-noise", "target-without-dp"],
)
def test_dp_it_cannot_do_is_one_line_before_training_and_nothing_is_recorded(
    overrides, message, tmp_path, capsys
):
    """Issue 50's fault sweep, DP edge cases. Epsilon 4.73 for round 1: dp-accounting's RDP
    for one Gaussian of multiplier 1, sampling rate 1, delta 1e-5."""
    store = tmp_path / "mlflow.db"
    argv = ["run", "debug/fast.yaml", f"--tracking-uri=sqlite:///{store}", *overrides]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"fedlgr: error: {message}"), err
    assert not store.exists()  # no run, no store


@pytest.mark.slow
def test_a_run_logs_the_accountants_epsilon_every_round_and_stops_at_its_target(
    synth_dir, cache_dir, tmp_path, capsys
):
    """4 clients at fraction 0.5 (Poisson), z = 2: round r's epsilon in MLflow's history,
    results.csv and the console is dp-accounting's after r releases; the target stops the
    run after the rounds it allows, FINISHED."""
    store = f"sqlite:///{tmp_path}/mlflow.db"
    z, rate, delta = 2.0, 0.5, 0.01
    target = privacy.epsilon(z, rate, 3, delta) + 1e-9  # three rounds fit, not four
    config = fast_config(
        synth_dir,
        cache_dir,
        store,
        "data.clients=4",
        "federated.rounds=6",
        "federated.fraction=0.5",
        "federated.dp.clip=0.5",
        f"federated.dp.noise_multiplier={z}",
        f"federated.dp.delta={delta}",
        f"federated.dp.target_epsilon={target}",
    )
    result = run_experiment(config)
    out = capsys.readouterr().out
    assert "stops after round 3 of 6" in out
    assert len(result.rounds) == 3
    client = mlflow.MlflowClient(store)
    run = client.get_run(result.run_id)
    assert run.info.status == "FINISHED"
    history = client.get_metric_history(result.run_id, "privacy/epsilon")
    expected = [privacy.epsilon(z, rate, r, delta) for r in (1, 2, 3)]
    assert [m.step for m in history] == [1, 2, 3]
    assert [m.value for m in history] == pytest.approx(expected, rel=1e-9)
    rows = results_csv(client, result.run_id)
    by_round = {int(r["round"]): float(r["privacy_epsilon"]) for r in rows}
    assert [by_round[r] for r in (1, 2, 3)] == pytest.approx(expected, rel=1e-9)
    for r, eps in zip((1, 2, 3), expected, strict=True):
        assert f"round {r}/3: " in out and f"epsilon {eps:.2f}" in out
    clip = client.get_metric_history(result.run_id, "privacy/clip")
    assert {m.value for m in clip} == {0.5}  # fixed clipping


def test_a_dp_run_draws_the_same_noise_again_for_its_seed(synth_dir, cache_dir):
    """Two runs of one seed give the same global model to the last bit; another seed
    another one."""

    def run(seed):
        config = fast_config(
            synth_dir,
            cache_dir,
            "sqlite://",
            "tracking.enabled=false",
            "federated.rounds=2",
            f"seed={seed}",
            "federated.dp.clip=1",
            "federated.dp.noise_multiplier=0.1",
            "federated.dp.delta=0.1",
        )
        return [r.mean("test/rmse") for r in run_experiment(config).rounds]

    first = run(0)
    assert run(0) == first
    assert run(1) != first


@pytest.mark.slow
@pytest.mark.parametrize(
    "method", ["FedRoot-EWC", "FedLGR", "SCAFFOLD", "FedRootOpt", "FedAvg-NR", "FedRootBN"]
)
def test_dp_composes_with_strategies_scopes_and_cl_methods(method, synth_dir, cache_dir):
    """A two-task run (one round each; plain FL: two rounds) of each under DP: every round
    released (epsilon after 2 releases), scores finite."""
    config = fast_config(
        synth_dir,
        cache_dir,
        "sqlite://",
        "tracking.enabled=false",
        f"method={method}",
        "continual.rounds_per_task=1",
        "federated.rounds=2",  # plain FL's (SCAFFOLD)
        "continual.lgr.epochs=2",
        "federated.dp.clip=1",
        "federated.dp.noise_multiplier=0.5",
        "federated.dp.delta=0.1",
    )
    assert config.federated.dp.enabled and config.total_rounds == 2
    result = run_experiment(config)
    spent = [r.server["privacy/epsilon"] for r in result.rounds]
    assert spent == pytest.approx([privacy.epsilon(0.5, 1.0, r, 0.1) for r in (1, 2)])
    assert all(math.isfinite(r.mean("test/rmse")) for r in result.rounds)


def test_batchnorm_running_statistics_stay_on_the_clients_under_dp():
    """Released with noise they broke the model (docs/privacy.md): under DP the shared
    tensors are the scope's without them; BatchNorm's weights and biases still travel."""
    plain = ServerSide(dp_config()).keys
    private = ServerSide(dp_config("federated.dp.clip=1")).keys
    statistics = [k for k in plain if k.endswith(("running_mean", "running_var"))]
    assert statistics and private == [k for k in plain if k not in statistics]
    bn_weights = [k.replace("running_mean", "weight") for k in statistics if "mean" in k]
    assert set(bn_weights) <= set(private)
