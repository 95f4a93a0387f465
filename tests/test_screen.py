"""The server's check of what it aggregates: an upload it cannot trust is refused, named
with its reason, and reaches nothing; the others are aggregated as if it had not come.

The cases are those a tester sent from one rostered robot (issue 37's table): non-finite,
huge or all-zero tensors, tensors of the wrong size or shape, a truncated tensor, and
sample counts of 10^12, -31, 0."""

from __future__ import annotations

import dataclasses
import math

import mlflow
import pytest
import torch

from fedlgr.core.messages import RoundPlan, TrainRes
from fedlgr.core.server.aggregate import weighted_mean
from fedlgr.core.server.screen import capped_counts, figures_refusal, oversized
from fedlgr.core.server.side import ServerSide
from fedlgr.errors import ConfigError
from fedlgr.shell.config import load_config
from fedlgr.shell.run.experiment import run_experiment
from tests.support.runs import fast_config

CLIENTS = 5


def server(*overrides: str, clients: int = CLIENTS) -> ServerSide:
    config = load_config(
        None,
        [
            f"data.clients={clients}",
            "data.modality=features",
            "model.root=mlp",
            "model.width=0.25",
            *overrides,
        ],
    )
    return ServerSide(config)


def honest(side: ServerSide, client: int, n: int = 10) -> TrainRes:
    """A small, seeded update of the global tensors (counters unchanged)."""
    g = torch.Generator().manual_seed(client)
    weights = {
        k: v + 1e-3 * torch.randn(v.shape, generator=g) if v.is_floating_point() else v.clone()
        for k, v in side.global_weights.items()
    }
    return TrainRes(client, weights, n)


def first_float(side: ServerSide) -> str:
    return next(k for k, v in side.global_weights.items() if v.is_floating_point() and v.ndim == 2)


def altered(side: ServerSide, how: str) -> TrainRes:
    """Client 2's upload, altered as the tester altered robot 2's."""
    res = honest(side, 2)
    key = first_float(side)
    w = res.weights
    if how == "nan":
        w[key] = torch.full_like(w[key], math.nan)
    elif how == "inf":
        w[key] = w[key].clone().index_fill_(0, torch.tensor([0]), math.inf)
    elif how == "x1e30":
        res.weights = {k: v * 1e30 if v.is_floating_point() else v for k, v in w.items()}
    elif how == "zeros":
        res.weights = {k: torch.zeros_like(v) for k, v in w.items()}
    elif how == "one element":
        w[key] = w[key].flatten()[:1]
    elif how == "extra dimension":
        w[key] = w[key].unsqueeze(0)
    elif how == "truncated":
        w[key] = w[key][:-1]
    elif how == "float64":
        w[key] = w[key].double()
    elif how == "missing key":
        del w[key]
    elif how == "extra key":
        w["top.secret"] = torch.zeros(1)
    elif how.startswith("n="):
        res.n_samples = eval(how[2:])
    return res


REASONS = {
    "nan": "holds values that are not finite",
    "inf": "holds values that are not finite",
    "x1e30": "x the others' median",
    "zeros": "x the others' median",
    "one element": "has shape [1], not",
    "extra dimension": "has shape [1, ",
    "truncated": "has shape [",
    "float64": "is float64, not float32",
    "missing key": "shared tensor(s) missing",
    "extra key": "tensor(s) that are not shared (top.secret, ...)",
    "n=10**12": "sample count 1000000000000 exceeds its 10 training scenes",
    "n=-31": "sample count -31 is not a positive whole number",
    "n=0": "sample count 0 is not a positive whole number",
    "n=2.5": "sample count 2.5 is not a positive whole number",
    "n=True": "sample count True is not a positive whole number",
}


@pytest.mark.parametrize("how", list(REASONS))
def test_an_altered_upload_is_refused_named_and_leaves_the_global_model_untouched(how):
    side = server()
    uploads = [altered(side, how) if c == 2 else honest(side, c, n=10 + c) for c in range(CLIENTS)]
    others = [u for u in uploads if u.client != 2]
    expected = weighted_mean(
        [(u.n_samples, u.weights) for u in others], side.keys, like=side.global_weights
    )
    capacity = {c: 10 + c for c in range(CLIENTS)}
    capacity[2] = 10
    refused = side.refusals(uploads, capacity)
    taken = side.screen(uploads, refused, side.update_norms(uploads, refused))
    assert [u.client for u in taken] == [0, 1, 3, 4]
    assert list(side.refused) == [2] and REASONS[how] in side.refused[2], side.refused
    side.update(*side.sums(taken), senders=len(taken))
    for key, value in side.global_weights.items():
        assert torch.equal(value, expected[key]), key  # as if client 2 had not sent
    why = side.refused[2]
    log = side.round_log(_plan(), side.table({}), 1.0)
    assert log.refused == {2: why} and side.refused == {}  # the next round starts clean
    assert log.metrics()["faults/refused"] == 1.0


def test_the_server_s_own_round_refuses_an_upload_without_knowing_the_split():
    """``ServerSide.aggregate`` (the Flower server's): every check but the sample-count
    bound, which needs the split; nothing is taken, nothing changes."""
    side = server()
    before = {k: v.clone() for k, v in side.global_weights.items()}
    side.aggregate([altered(side, "nan")])
    assert "not finite" in side.refused[2]
    assert all(torch.equal(v, before[k]) for k, v in side.global_weights.items())
    side.aggregate([honest(side, 0), altered(side, "n=10**12")])  # no bound: taken
    assert side.refused == {}


def test_the_norm_check_compares_with_the_median_of_the_others_and_can_be_turned_off():
    """Each norm against the median of the others' (1.5 for client 2 here): a client is
    never its own yardstick, so two uploads are compared and a round of one is not."""
    assert oversized({0: 1.0, 1: 2.0, 2: 15.0}, 10.0) == {}  # 15 = 10 x the others' 1.5
    assert list(oversized({0: 1.0, 1: 2.0, 2: 15.1}, 10.0)) == [2]
    assert list(oversized({0: 1.0, 1: 1e6}, 10.0)) == [1]  # two uploads: the other's 1
    assert oversized({0: 1e6}, 10.0) == {}  # one upload: nothing to compare with
    assert oversized({0: 1.0, 1: 2.0, 2: 1e9}, 0.0) == {}  # federated.norm_ratio=0: off
    assert oversized({0: 0.0, 1: 0.0, 2: 0.0}, 10.0) == {}  # nobody moved
    assert list(oversized({0: 0.0, 1: 0.0, 2: 5.0}, 10.0)) == [2]  # only one moved
    side = server("federated.norm_ratio=0")
    uploads = [honest(side, c) for c in (0, 1)] + [altered(side, "x1e30")]
    refused = side.refusals(uploads)
    assert side.screen(uploads, refused, side.update_norms(uploads, refused)) == uploads


def test_norm_ratio_below_one_is_refused_at_load():
    from fedlgr.errors import ConfigError

    with pytest.raises(ConfigError, match=r"federated.norm_ratio=0.5: must be 0 \(no check\)"):
        server("federated.norm_ratio=0.5")


def _plan():
    from fedlgr.core.messages import RoundPlan

    return RoundPlan(1)


def test_a_run_with_a_poisoned_client_finishes_names_it_and_logs_the_count(
    synth_dir, cache_dir, store, monkeypatch, capsys
):
    """In one process: client 1's round-2 upload is NaN; the server refuses it, the run
    goes on with client 0's (before: every client failed round 3 on a NaN loss), the
    console and MLflow name client 1, and ``faults/refused`` counts it at step 2."""
    from fedlgr.core.client.side import ClientSide

    original = ClientSide.upload
    uploads = {0: 0, 1: 0}

    def poisoned(self, client):
        weights = original(self, client)
        uploads[client.index] += 1
        if client.index == 1 and uploads[1] == 2:  # its round-2 upload
            return {k: v * math.nan if v.is_floating_point() else v for k, v in weights.items()}
        return weights

    monkeypatch.setattr(ClientSide, "upload", poisoned)
    config = fast_config(
        synth_dir, cache_dir, store, "method=FedAvg", "federated.rounds=3", "data.modality=features"
    )
    result = run_experiment(config)
    out = capsys.readouterr().out
    assert "round 2/3: refused client 1's upload: " in out and "not finite" in out
    client = mlflow.MlflowClient(store)
    run = client.get_run(result.run_id)
    assert run.info.status == "FINISHED"
    assert [
        (m.step, m.value) for m in client.get_metric_history(run.info.run_id, "faults/refused")
    ] == [(2, 1.0)]
    assert run.data.tags["fedlgr.not_taken"].startswith("round 2: client 1 (upload: ")
    assert math.isfinite(run.data.metrics["test/rmse"])


@pytest.mark.parametrize(
    ("figures", "why"),
    [
        ({"test/rmse": 0.9, "test/pcc": 0.5, "cost/cpu_s": 1.0}, None),
        ({"test/pcc": 1.000001, "test/ccc": -1.0}, None),  # float32's slack at the ends
        ({"test/rmse": math.nan}, "test/rmse = nan is not finite"),
        ({"test/pcc": math.inf}, "test/pcc = inf is not finite"),
        ({"test/pcc": 1.5}, "test/pcc = 1.5 is out of [-1, 1]"),
        ({"task/circle/ccc": -2.0}, "task/circle/ccc = -2 is out of [-1, 1]"),
        ({"test/rmse": -0.1}, "test/rmse = -0.1 is below 0"),
        ({"test/mse/vacuum": -1.0}, "test/mse/vacuum = -1 is below 0"),
        ({"test/ccc/vacuum": 1.2}, "test/ccc/vacuum = 1.2 is out of [-1, 1]"),
        ({"train/loss": -0.5}, "train/loss = -0.5 is below 0"),
        ({"lgr/recon_mse": -0.5}, "lgr/recon_mse = -0.5 is below 0"),
        ({"cost/bytes_up": -5.0}, "cost/bytes_up = -5 is below 0"),
        ({"test/rmse": "0.9"}, "test/rmse = '0.9' is not a number"),
        ({"test/rmse": True}, "test/rmse = 'True' is not a number"),
        ({"secret/figure": 1.0}, "'secret/figure' is not a figure of this run"),
    ],
)
def test_a_robots_reported_figures_are_checked_by_hand(figures, why):
    keys = {"test/rmse", "test/pcc", "test/ccc", "task/circle/ccc", "test/mse/vacuum"}
    keys |= {"test/ccc/vacuum", "train/loss", "lgr/recon_mse", "cost/cpu_s", "cost/bytes_up"}
    assert figures_refusal(figures, keys) == why


def honest_with_payload(side: ServerSide, client: int, n: int = 10) -> TrainRes:
    """A small seeded update of the global tensors, and for SCAFFOLD the change of the
    control variate it gives (the strategy's payload)."""
    g = torch.Generator().manual_seed(100 + client)
    weights = {
        k: v + 1e-3 * torch.randn(v.shape, generator=g) if v.is_floating_point() else v.clone()
        for k, v in side.global_weights.items()
    }
    # option II's change, as an honest client computes it from its K local steps
    steps, lrs = side.fewest_steps(n), side.learning_rates
    control = getattr(side.strategy, "control", {})
    payload = {
        f"scaffold/{k}": -c + (side.global_weights[k] - weights[k]) / (steps * lrs[k])
        for k, c in control.items()
    }
    return TrainRes(client, weights, n, {}, payload)


def scaled(side: ServerSide, res: TrainRes, factor: float) -> TrainRes:
    g = side.global_weights
    res.weights = {k: g[k] + factor * (v - g[k]) for k, v in res.weights.items()}
    return res


def finite(weights) -> bool:
    return all(bool(torch.isfinite(v).all()) for v in weights.values())


def test_a_nan_scaffold_payload_is_refused_and_leaves_the_control_variate_finite():
    """SCAFFOLD: client 2's tensors are honest but its control-variate change (the payload
    it uploads beside them, which a robot sends over Flower too) is NaN. Nothing screens
    the payload: the upload is taken and the server's control variate c turns NaN - sent to
    every client next round, added to every gradient.
    Found by the independent fault sweep of issue 37."""
    side = server("method=SCAFFOLD", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    uploads[2].payload = {k: v * math.nan for k, v in uploads[2].payload.items()}
    side.aggregate(uploads)
    assert 2 in side.refused, side.refused
    assert finite(side.strategy.control)


def test_a_huge_scaffold_payload_does_not_reach_the_control_variate():
    """As above with a finite x1e30 payload: c becomes ~1e29 (the mean over 5 clients).
    Found by the independent fault sweep of issue 37."""
    side = server("method=SCAFFOLD", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    reference = server("method=SCAFFOLD", clients=5)
    reference.aggregate([u for u in uploads if u.client != 2])
    uploads[2].payload = {k: v * 1e30 for k, v in uploads[2].payload.items()}
    side.aggregate(uploads)
    assert 2 in side.refused, side.refused
    for k, c in side.strategy.control.items():
        assert torch.equal(c, reference.strategy.control[k]), k


def test_a_scaffold_payload_of_another_shape_is_refused_not_broadcast():
    """A 0-d payload tensor for every control variate is broadcast over it by the sum.
    Found by the independent fault sweep of issue 37."""
    side = server("method=SCAFFOLD", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    uploads[2].payload = {
        k: v.flatten()[:1].reshape(()) * 1e3 for k, v in uploads[2].payload.items()
    }
    side.aggregate(uploads)
    assert 2 in side.refused, side.refused


def test_a_payload_with_an_extra_key_is_refused_not_a_keyerror():
    """An upload whose payload has a key the strategy does not use (a robot adding a
    payload record of its own, under FedAvg) ends the round with KeyError in the payload
    sums instead of being refused and named.
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    uploads[2].payload = {"scaffold/evil": torch.full((3,), math.nan)}
    side.aggregate(uploads)  # KeyError: 'scaffold/evil'
    assert 2 in side.refused, side.refused


def test_a_scaffold_upload_without_its_payload_is_refused_not_a_keyerror():
    """Found by the independent fault sweep of issue 37."""
    side = server("method=SCAFFOLD", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    uploads[2].payload = {}
    uploads[3].payload = dict(list(uploads[3].payload.items())[:-1])  # one key short
    side.aggregate(uploads)  # KeyError in _payload_sums / Scaffold.take_payloads
    assert {2, 3} <= set(side.refused), side.refused


def test_with_two_uploads_an_update_a_million_times_the_other_is_refused():
    """The norm check compares with the round's median over every upload, the candidate's
    own included: with two uploads the median is their mean, so no update, however large
    (x1e6 here, x1e30 alike), is ever over 10 x it. Issue 37 asks for an update 'far beyond
    the round's others' to be refused; a federation of two robots takes it.
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=2)
    uploads = [honest_with_payload(side, 0), scaled(side, honest_with_payload(side, 1), 1e6)]
    side.aggregate(uploads)
    assert list(side.refused) == [1], side.refused


def test_a_huge_update_is_refused_when_the_others_did_not_move():
    """Where the round's median update norm is 0 (two of three clients send the global
    tensors back: they had nothing to learn, or a frozen root under FedRoot) the norm check
    is skipped, and a third client's x1e3 model becomes a third of the global one.
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=3)
    same = {k: v.clone() for k, v in side.global_weights.items()}
    uploads = [TrainRes(0, dict(same), 10), TrainRes(1, dict(same), 10)]
    bad = honest_with_payload(side, 2)
    bad.weights = {k: v * 1e3 for k, v in bad.weights.items()}
    side.aggregate([*uploads, bad])
    assert list(side.refused) == [2], side.refused


def test_a_sample_count_beyond_float_range_is_refused_not_an_overflowerror():
    """Without a known capacity (ServerSide.aggregate, a robot without roster scenes) a
    whole number too large for a float ends the round with OverflowError.
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    uploads[2].n_samples = 10**400
    side.aggregate(uploads)
    assert 2 in side.refused, side.refused


def test_a_sparse_tensor_upload_is_refused_not_a_traceback():
    """The finiteness check calls torch.isfinite(...).all() on a sparse COO tensor:
    NotImplementedError (aten::ne.Scalar on SparseCPU).
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    key = next(k for k, v in side.global_weights.items() if v.ndim == 2)
    uploads[2].weights[key] = uploads[2].weights[key].to_sparse()
    side.aggregate(uploads)
    assert 2 in side.refused, side.refused


def test_a_robot_s_figure_too_large_for_a_float_is_refused_not_an_overflowerror():
    """Found by the independent fault sweep of issue 37."""
    from fedlgr.core.server.screen import figures_refusal

    assert figures_refusal({"test/rmse": 10**400}, {"test/rmse"}) is not None


def test_an_upload_that_makes_a_running_variance_negative_does_not_reach_the_global_model():
    """One BatchNorm running variance set to -20 in an otherwise honest upload: finite, of
    the right shape and dtype, and its update norm (~21) within 10 x the round's median
    (~3, honest updates of 0.01 per value). FedAvg takes it and the global running variance
    there is (4 x 1 - 20) / 5 < 0: the global model then answers NaN for every scene - the
    effect of the NaN upload issue 37 set out to stop, from a finite one (simulated runs
    show it too: attack=noise on a round of two uploads left every later score NaN while
    the run ended FINISHED).
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=5)
    key = next(k for k in side.global_weights if k.endswith("running_var"))
    uploads = []
    for c in range(5):
        g = torch.Generator().manual_seed(c)
        res = TrainRes(
            c,
            {
                k: v + 0.01 * torch.randn(v.shape, generator=g)
                for k, v in side.global_weights.items()
            },
            10,
        )
        uploads.append(res)
    uploads[2].weights[key] = (
        uploads[2].weights[key].clone().index_fill_(0, torch.tensor([0]), -20.0)
    )
    side.aggregate(uploads)
    assert bool((side.global_weights[key] >= 0).all()), side.global_weights[key][:3]


def test_two_uploads_for_one_client_are_both_refused_and_an_unknown_client_too():
    """The re-run sweep: two uploads claiming client 2 in one round (NaN, then honest)
    left the global model NaN - the refusals were keyed by client, so the honest one's
    verdict overwrote the NaN one's; and client 9 of a 5-client run was taken with any
    sample count (no capacity is known for it).
    Found by the independent fault sweep of issue 37."""
    side = server("method=FedAvg", clients=5)
    uploads = [honest_with_payload(side, c) for c in range(5)]
    nan = honest_with_payload(side, 2)
    nan.weights = {k: v * math.nan if v.is_floating_point() else v for k, v in nan.weights.items()}
    stranger = honest_with_payload(side, 9, n=10**6)
    side.aggregate([nan, *uploads, stranger])
    assert side.refused == {
        2: "upload: 2 uploads in one round",
        9: "upload: no client 9 in data.clients=5",
    }
    assert finite(side.global_weights)


def test_sample_counts_are_capped_at_k_times_the_others_median_by_hand():
    """Issue 50: without a roster's scenes a robot claiming 10x its samples weighed 10/12.
    Counts (100, 120, 1000), cap 3: client 2's others' median is 110 -> capped at 330;
    client 1's is 550 (1650 > 120): not capped. Two clients: each is the other's yardstick;
    one: nothing to compare; cap 0: none."""
    assert capped_counts({0: 100, 1: 120, 2: 1000}, 3.0) == {2: 330}
    assert capped_counts({0: 100, 1: 1000}, 3.0) == {1: 300}
    assert capped_counts({0: 100}, 3.0) == {} and capped_counts({0: 1, 1: 99}, 0) == {}


def test_a_capped_count_weighs_its_cap_and_is_reported_but_a_rostered_bound_is_kept():
    """Three uploads of 10, 10 and 1000 samples, nothing bounding client 2: it weighs 30
    (the global tensors are the mean weighted 10, 10, 30) and the round's record names it;
    with client 2 bounded (its 1000 scenes, a roster's ``scenes``) it keeps its 1000; under
    federated.count_cap=0 too. A median weighs none: nothing is capped there."""
    side = server(clients=3)
    uploads = [honest(side, 0, 10), honest(side, 1, 10), honest(side, 2, 1000)]
    key = first_float(side)

    def mean(weights):
        total = sum(weights)
        return (
            sum(w * r.weights[key].double() for w, r in zip(weights, uploads, strict=True)) / total
        )

    side.aggregate(uploads)
    assert torch.allclose(side.global_weights[key].double(), mean([10, 10, 30]), atol=1e-6)
    log = side.round_log(RoundPlan(1, 0), side.table({}), 1.0)
    assert log.capped == {
        2: "sample count 1000 capped at 30 (3 x the round's others' median; no roster "
        "scenes bound it)"
    }
    assert log.metrics()["faults/capped"] == 1.0
    assert log.rows()[2]["fault"] == log.capped[2]
    robust = server("federated.strategy=median", clients=3)  # weighs every upload 1
    robust.aggregate(uploads)
    assert robust.capped == {} and robust.refused == {}  # the fault sweep's case 3
    for bounded in (server(clients=3), server("federated.count_cap=0", clients=3)):
        bounded.aggregate(uploads, capacity={2: 1000})
        assert torch.allclose(bounded.global_weights[key].double(), mean([10, 10, 1000]), atol=1e-6)


def test_a_scaffold_payload_that_is_not_its_updates_change_is_refused_by_hand():
    """Issue 50: a payload x8 passed every check (RMSE 1.169 against 0.747 without it).
    Option II makes Delta c_i + c = (x - y_i) / (K lr): with c not 0, x8 lies off the
    update's direction; with c = 0 (round 1) it claims K / 8 = 1.25 local steps, fewer than
    the 10 its 10 scenes train (2 epochs of 5 batches of 2). The honest payload of the same
    upload passes."""
    overrides = ("method=SCAFFOLD", "train.epochs=2", "train.batch_size=2")
    side = server(*overrides, clients=3)
    steps = side.fewest_steps(10)
    assert steps == 10  # 2 epochs x ceil(10 / 2)
    upload = honest_with_payload(side, 0)
    payload = side.strategy.payload_refusal
    lrs = side.learning_rates
    assert payload(upload, side.global_weights, steps, lrs) is None
    x8 = dataclasses.replace(upload, payload={k: 8 * v for k, v in upload.payload.items()})
    assert payload(x8, side.global_weights, steps, lrs) == (
        "scaffold payload is that of 1.25 local steps, fewer than the 10 its 10 scenes train"
    )
    side.strategy.control = {k: torch.full_like(c, 0.5) for k, c in side.strategy.control.items()}
    upload = honest_with_payload(side, 0)
    assert payload(upload, side.global_weights, steps, lrs) is None
    x8 = dataclasses.replace(upload, payload={k: 8 * v for k, v in upload.payload.items()})
    why = payload(x8, side.global_weights, steps, lrs)
    assert why.startswith("scaffold payload is not its update's control-variate change (off")
    # in a round: refused and named, the others taken
    uploads = [honest_with_payload(side, c) for c in range(3)]
    uploads[2] = dataclasses.replace(
        uploads[2], payload={k: 8 * v for k, v in uploads[2].payload.items()}
    )
    side.aggregate(uploads)
    assert list(side.refused) == [2] and "control-variate change" in side.refused[2]


def test_a_payload_far_over_the_others_is_refused_by_its_own_norm():
    """The payload's norm is screened apart from the update's: the same rule,
    federated.norm_ratio x the others' median. By hand on payload norms 1, 1.2, 30."""
    assert oversized({0: 1.0, 1: 1.2, 2: 30.0}, 10, "payload") == {
        2: "payload norm 30 is over 10 x the others' median 1.1"
    }


def test_a_replayed_upload_is_refused_as_stale():
    """Issue 50: a robot sending again an upload it sent before was never noticed. The
    server keeps each upload's fingerprint: the same tensors, payload and count again are
    refused (also after a checkpoint), another client's equal upload is not its replay."""
    side = server(clients=3)
    first = [honest(side, c) for c in range(3)]
    side.aggregate(first)
    assert side.refused == {}
    again = [honest(side, 0, 11), first[1], dataclasses.replace(first[1], client=2)]
    restored = server(clients=3)
    restored.load_state_dict(side.state_dict(), "cpu")
    for s in (side, restored):
        s.aggregate(again)
        assert s.refused == {1: "upload: stale: identical to an upload it sent before (a replay)"}


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("0.5", r"federated.count_cap=0.5: must be 0 \(no cap\) or at least 1 "),
        ("-1", r"federated.count_cap=-1.0: must be >= 0"),
    ],
)
def test_a_count_cap_below_one_is_refused_at_load(value, message):
    """A cap under 1 would cut every honest count below the others' median: refused, naming
    the setting; 0 turns the cap off."""
    with pytest.raises(ConfigError, match=message):
        load_config(None, [f"federated.count_cap={value}"])
    assert load_config(None, ["federated.count_cap=0"]).federated.count_cap == 0
