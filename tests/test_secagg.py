"""Secure aggregation (``deploy.secagg``) without processes: its settings refused in one
line where SecAgg+ cannot apply, the robots' ClientApp mod passing plain messages through
unchanged, and the vector layout - the server's release from the sum of the robots'
vectors is ServerSide's aggregation of the same uploads, plain and under DP. The protocol
itself runs on real processes in tests/test_flower.py."""

from __future__ import annotations

import dataclasses
import math

import flwr.compat.common.recorddict_compat as compat
import numpy as np
import pytest
import torch
from flwr.app import ConfigRecord, Context, Message, RecordDict
from flwr.client.mod import secaggplus_mod
from flwr.common import Code, Error, FitRes, Status, ndarrays_to_parameters
from flwr.common.secure_aggregation.quantization import dequantize, quantize
from flwr.common.secure_aggregation.secaggplus_constants import RECORD_KEY_CONFIGS, Key, Stage
from flwr.supercore.task_identity import TaskIdentity

from fedlgr.core.messages import RoundPlan, TrainIns, TrainRes
from fedlgr.core.privacy import UNCLIPPED
from fedlgr.core.server.side import ServerSide
from fedlgr.errors import ConfigError
from fedlgr.shell.config import load_config
from fedlgr.shell.deploy.flower import masked, wire
from fedlgr.shell.deploy.flower.client_app import secure_mod
from fedlgr.shell.deploy.flower.link import decode, encode
from fedlgr.shell.deploy.flower.secure import Adapter, secure_sum, unpack
from tests.support.runs import FAST

ON = "deploy.secagg.enabled=true"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["method=FedRootKrum"],
            "deploy.secagg.enabled with federated.strategy=krum: a krum aggregate needs every",
        ),
        (["data.clients=1"], "deploy.secagg.enabled: a round chooses 1 robot (data.clients=1"),
        (
            [
                "data.clients=4",
                "federated.fraction=0.5",
                "federated.dp.clip=1",
                "federated.dp.delta=0.01",
            ],
            "deploy.secagg.enabled with federated.dp and federated.fraction=0.5: DP samples",
        ),
        (["deploy.secagg.max_samples=1000000"], "deploy.secagg.max_samples=1000000: with"),
        (
            [
                "deploy.secagg.clipping_range=0.4",
                "federated.dp.clip=1",
                "federated.dp.clipping=adaptive",
                "federated.dp.count_noise=1",
                "federated.dp.delta=0.1",
            ],
            "deploy.secagg.clipping_range=0.4 with federated.dp: each robot's weight 1 (and",
        ),
        (["deploy.secagg.threshold=0"], "deploy.secagg.threshold=0.0: must be in (0, 1]"),
        (["deploy.secagg.quantization_range=8388608"], "deploy.secagg.quantization_range="),
    ],
    ids=[
        "krum",
        "one-robot",
        "dp-poisson",
        "count-unreadable",
        "bit-clipped",
        "threshold",
        "modulus",
    ],
)
def test_secagg_is_refused_in_one_line_where_it_cannot_apply(overrides, message):
    with pytest.raises(ConfigError) as found:
        load_config(FAST, [ON, *overrides])
    assert str(found.value).startswith(message) and "\n" not in str(found.value)


def test_secagg_is_off_by_default_and_allowed_with_adaptive_dp():
    assert not load_config(FAST, []).deploy.secagg.enabled
    dp = ["federated.dp.clip=1", "federated.dp.clipping=adaptive", "federated.dp.count_noise=1"]
    assert load_config(FAST, [ON, *dp, "federated.dp.delta=0.1"]).deploy.secagg.enabled


@pytest.fixture
def robot_process(monkeypatch):
    """What Flower sets in a ClientApp's process before it makes messages: its task's
    run, node and task."""
    monkeypatch.setattr(TaskIdentity, "_run_id", 1)
    monkeypatch.setattr(TaskIdentity, "_node_id", 7)
    monkeypatch.setattr(TaskIdentity, "_task_id", 1)


def message(content: RecordDict) -> Message:
    return Message(content, dst_node_id=7, message_type="train")


def context() -> Context:
    return Context(run_id=1, node_id=7, node_config={}, state=RecordDict(), run_config={})


def test_the_robots_mod_passes_plain_messages_through_unchanged_and_answers_secagg_ones(
    robot_process,
):
    """A fedlgr train message without SecAgg+'s record reaches the robot as it was sent
    (the same object) and its reply leaves as the robot made it; a SecAgg+ setup message
    is answered by Flower's mod (two public keys), never by the robot."""
    plan = RoundPlan(1, 0, True, True)
    content = wire.encode_train_ins(TrainIns(plan, {"w": torch.ones(3)}, {}), "seed: 0", client=0)
    seen, replies = [], []

    def robot(msg: Message, ctxt: Context) -> Message:
        seen.append(msg)
        replies.append(Message(RecordDict({"report": ConfigRecord({"client": 0})}), reply_to=msg))
        return replies[-1]

    plain = message(content)
    assert secure_mod(plain, context(), robot) is replies[0]
    assert seen == [plain] and seen[0].content is content
    setup = {
        Key.STAGE: Stage.SETUP,
        Key.SAMPLE_NUMBER: 2,
        Key.SHARE_NUMBER: 2,
        Key.THRESHOLD: 2,
        Key.CLIPPING_RANGE: 1.0,
        Key.TARGET_RANGE: 1 << 22,
        Key.MOD_RANGE: 1 << 32,
        Key.MAX_WEIGHT: 1.0,
    }
    keys = secure_mod(
        message(RecordDict({RECORD_KEY_CONFIGS: ConfigRecord(setup)})), context(), robot
    )
    answer = keys.content.config_records[RECORD_KEY_CONFIGS]
    assert isinstance(answer[Key.PUBLIC_KEY_1], bytes) and len(seen) == 1


def uploads(server: ServerSide, counts: list[int], scale: float) -> list[TrainRes]:
    """Uploads of known updates: the global tensors plus seeded noise, and the payloads
    they give."""
    made = torch.Generator().manual_seed(3)
    out = []
    for client, n in enumerate(counts):
        weights = {
            k: g + scale * torch.randn(g.shape, generator=made).to(g.dtype)
            for k, g in server.global_weights.items()
        }
        # SCAFFOLD's option II change from c = 0, as the robot computes it (the server
        # checks it is: Scaffold.payload_refusal)
        steps, lrs = server.fewest_steps(n), server.learning_rates
        payload = {
            k: (server.global_weights[k[len("scaffold/") :]] - weights[k[len("scaffold/") :]])
            / (steps * lrs[k[len("scaffold/") :]])
            for k in server.strategy.payload_template()
        }
        out.append(TrainRes(client, weights, n, {}, payload))
    return out


def released(config, results: list[TrainRes]) -> tuple[ServerSide, ServerSide]:
    """The same uploads aggregated by ServerSide (in the clear) and released from the sum
    of the robots' vectors (no quantisation here: the sum is exact in float64)."""
    plain, secure = ServerSide(config), ServerSide(config)
    plain.aggregate(results)
    clip = 0.0 if secure.privacy is None else secure.privacy.bound
    record = masked.message_settings(config.deploy.secagg, clip)
    vectors = [masked.robot_vector(r, secure.global_weights, record)[0] for r in results]
    sums, total, payloads = unpack(
        np.sum(vectors, axis=0), len(results), secure, config.deploy.secagg
    )
    secure.update(sums, total, payloads, len(results))
    return plain, secure


def assert_same_globals(plain: ServerSide, secure: ServerSide) -> None:
    for key, value in plain.global_weights.items():
        # the same sums to float64 rounding, then each side's cast to float32 and the
        # strategy's float32 server step (SCAFFOLD's): two ulps at most, an ulp being at
        # most 2^-23 of the value
        error = (secure.global_weights[key].double() - value.double()).abs()
        assert bool((error <= 2.0**-22 * value.double().abs() + 1e-12).all()), key


def test_the_sum_of_the_robots_vectors_releases_the_sample_weighted_mean_and_payload_sums():
    """SCAFFOLD (its control-variate changes travel as the payload, summed plainly), three
    robots of 5, 9 and 12 samples: the global tensors and control variates released from
    the vectors' sum are ServerSide's from the same uploads."""
    # option II's changes of these updates are large: no robot clips them here
    bound = "deploy.secagg.norm_bound=1e6"
    config = load_config(FAST, [ON, "method=SCAFFOLD", "data.clients=3", bound])
    plain, secure = released(config, uploads(ServerSide(config), [5, 9, 12], 0.01))
    assert_same_globals(plain, secure)
    for key, value in plain.strategy.state_dict()["control"].items():
        theirs = secure.strategy.state_dict()["control"][key]
        assert torch.allclose(theirs.double(), value.double(), rtol=0, atol=1e-9), key


def test_under_dp_robots_clip_their_own_updates_and_adaptive_clipping_gets_the_count():
    """DP with adaptive clipping and no noise (the count's noise is seeded): robots clip
    their own updates (one is over the clip norm, one within) and send the unclipped bit
    in the sum; the release and the next clip norm are those of the server that clipped
    the same uploads itself."""
    dp = ["federated.dp.clip=0.5", "federated.dp.noise_multiplier=0", "federated.dp.delta=0.1"]
    dp += ["federated.dp.clipping=adaptive", "federated.dp.count_noise=0.5"]
    config = load_config(FAST, [ON, "method=FedAvg", *dp])
    server = ServerSide(config)
    results = uploads(server, [5, 9], 0.0)
    results[0] = dataclasses.replace(  # far over the clip norm
        results[0], weights={k: g + 0.1 for k, g in server.global_weights.items()}
    )
    results[1] = dataclasses.replace(  # well within it
        results[1], weights={k: g + 1e-6 for k, g in server.global_weights.items()}
    )
    plain, secure = released(config, results)
    assert_same_globals(plain, secure)
    assert secure.privacy.bound == pytest.approx(plain.privacy.bound, rel=1e-12)
    assert secure.privacy.bound != 0.5  # it moved


def secagg_sum(vectors: list[np.ndarray], secagg) -> np.ndarray:
    """The sum SecAgg+ gives the server: each robot's vector quantised as Flower's mod does
    it (weight 1: ratio 1), the integers summed (the masks cancel), dequantised and shifted
    as Flower's workflow does it, times the robots (the workflow gives their mean)."""
    c, levels = secagg.clipping_range, secagg.quantization_range
    state = np.random.get_state()  # quantize rounds stochastically with numpy's generator
    np.random.seed(0)
    try:
        ints = sum(quantize([v], c, levels)[0].astype(np.int64) for v in vectors)
    finally:
        np.random.set_state(state)
    return dequantize([ints], c, levels)[0] - (len(vectors) - 1) * c


def test_the_centred_bits_sum_is_read_back_exactly_from_a_quantised_secure_sum():
    """Adaptive clipping under SecAgg+ with Q = 2^22 - 1 levels over [-1, 1], where +-1/2
    falls between two of them: three robots, one update over the clip norm and two
    within, send -1/2, +1/2, +1/2; the sum the server reads is off by under 3 levels, and
    is read back as 2 - 3/2 = 1/2 exactly - the count the server that clips itself
    releases, so the clip norm moves the same."""
    dp = ["federated.dp.clip=0.5", "federated.dp.noise_multiplier=0", "federated.dp.delta=0.1"]
    dp += ["federated.dp.clipping=adaptive", "federated.dp.count_noise=0.5"]
    config = load_config(
        FAST,
        [ON, "method=FedAvg", "data.clients=3", "deploy.secagg.quantization_range=4194303", *dp],
    )
    plain, secure = ServerSide(config), ServerSide(config)
    results = uploads(plain, [5, 9, 12], 1e-7)
    results[0] = dataclasses.replace(  # far over the clip norm
        results[0], weights={k: g + 0.1 for k, g in plain.global_weights.items()}
    )
    plain.aggregate(results)
    record = masked.message_settings(config.deploy.secagg, 0.5)
    vectors = [masked.robot_vector(r, secure.global_weights, record)[0] for r in results]
    assert [v[-1] for v in vectors] == [-0.5, 0.5, 0.5]  # the layout's last value: the bit
    summed = secagg_sum(vectors, config.deploy.secagg)
    step = 2 / config.deploy.secagg.quantization_range
    # each robot's value stochastically rounded: off by under one level each (the float
    # arithmetic of dequantising adds ~1e-16, far below a level of 4.8e-7)
    assert summed[-1] != 0.5 and abs(summed[-1] - 0.5) < 3 * step
    sums, total, payloads = unpack(summed, 3, secure, config.deploy.secagg)
    assert total == 3.0 and payloads[UNCLIPPED].item() == 0.5
    secure.update(sums, total, payloads, 3)
    assert secure.privacy.count == plain.privacy.count
    assert secure.privacy.bound == plain.privacy.bound != 0.5


def test_robots_clip_to_the_norm_bound_and_a_sum_no_honest_robots_send_is_refused():
    """Three robots of 5, 9 and 12 samples, no DP: each moves every value by 0.01 (an update of
    norm ~3.7 on the tiny model), so each clips it to deploy.secagg.norm_bound=0.5 - all in
    one direction, the worst honest case: the quantised sum's mean update is 0.5 (+ the
    quantisation) and is taken. With one robot's update x 1000 unclipped in its place, the sum is
    refused, named by its mean update's norm; under DP, by the clip norm."""
    config = load_config(
        FAST, [ON, "method=FedAvg", "data.clients=3", "deploy.secagg.norm_bound=0.5"]
    )
    secagg = config.deploy.secagg
    server = ServerSide(config)
    like = server.global_weights.items()
    results = [
        dataclasses.replace(r, weights={k: g + 0.01 * g.is_floating_point() for k, g in like})
        for r in uploads(server, [5, 9, 12], 0.0)
    ]
    record = masked.message_settings(secagg, 0.0)
    made = [masked.robot_vector(r, server.global_weights, record) for r in results]
    sizes = [size for _, _, size in made]
    assert all(3 < size < 4 for size in sizes), sizes  # 0.01 x sqrt(~140 000 values)
    vectors = [vector for vector, _, _ in made]
    for vector, r in zip(vectors, results, strict=True):  # n / W x the clipped update
        assert np.linalg.norm(vector[:-1]) == pytest.approx(0.5 * r.n_samples / 1000, rel=1e-12)
    sums, total, _ = unpack(secagg_sum(vectors, secagg), 3, server, secagg)
    assert total == 26.0
    mean = {k: sums[k] / total - g.double() for k, g in server.global_weights.items()}
    # each value of the mean off by under error_bound: its norm by under that x sqrt(values)
    slack = masked.error_bound(secagg, 3, total, dp=False) * math.sqrt(vectors[0].size - 1)
    size = float(torch.cat([v.flatten() for v in mean.values()]).norm())
    assert abs(size - 0.5) < slack < 0.05
    vectors[0][:-1] = 1000 * (vectors[0][:-1] / 0.5 * sizes[0])  # unclipped, x 1000
    with pytest.raises(
        ValueError,
        match=r"its mean update's norm [0-9.e+]+ is over deploy\.secagg\.norm_bound=0\.5 ",
    ):
        unpack(secagg_sum(vectors, secagg), 3, server, secagg)
    dp = ["federated.dp.clip=0.5", "federated.dp.noise_multiplier=0", "federated.dp.delta=0.1"]
    config = load_config(FAST, [ON, "method=FedAvg", "data.clients=3", *dp])
    server = ServerSide(config)
    record = masked.message_settings(config.deploy.secagg, server.privacy.bound)
    vectors = [masked.robot_vector(r, server.global_weights, record)[0] for r in results]
    secagg = config.deploy.secagg
    unpack(secagg_sum(vectors, secagg), 3, server, secagg)  # 3 clipped updates: taken
    vectors[0][:-2] *= 1000  # not its weight 1 nor its bit
    with pytest.raises(
        ValueError, match=r"its updates' norm [0-9.e+]+ is over 3 robots x the clip norm 0\.5 "
    ):
        unpack(secagg_sum(vectors, secagg), 3, server, secagg)


def test_the_error_bound_follows_the_quantisation_step():
    """robots x 2c/Q, over the summed weight (n / max_samples) without DP."""
    secagg = load_config(FAST, [ON]).deploy.secagg
    step = 2 * secagg.clipping_range / secagg.quantization_range
    assert masked.error_bound(secagg, 3, 3000.0, dp=False) == pytest.approx(3 * step * 1000 / 3000)
    assert masked.error_bound(secagg, 3, 3.0, dp=True) == pytest.approx(3 * step)


class Loopback:
    """A grid within this process for SecAgg+'s server side: each message goes, encoded and decoded
    as on the wire, to its node's own ``secaggplus_mod`` (Flower's robot side, unchanged), whose
    training answers the node's ``vectors`` entry; a node in ``leaves`` answers nothing from that
    stage on."""

    def __init__(self, vectors: dict[int, np.ndarray], leaves: dict[int, str]):
        self.vectors, self.leaves = vectors, leaves
        self.contexts = {
            n: Context(run_id=1, node_id=n, node_config={}, state=RecordDict(), run_config={})
            for n in vectors
        }
        self.gone: set[int] = set()

    def send_and_receive(self, messages, *, timeout=None) -> list[Message]:
        replies = []
        for m in messages:
            node = m.metadata.dst_node_id
            if self.leaves.get(node) == m.content.config_records[RECORD_KEY_CONFIGS][Key.STAGE]:
                self.gone.add(node)
            if node in self.gone:
                continue
            # a copy, as a robot receives it (the mod changes it); an error, as a robot's
            # ClientApp answers one
            sent = Message(decode(encode(m.content)), dst_node_id=node, message_type="train")
            try:
                replies.append(secaggplus_mod(sent, self.contexts[node], self.train(node)))
            except Exception as err:  # any, as Flower's ClientApp answers it
                replies.append(Message(Error(0, repr(err)), reply_to=sent))
        return replies

    def train(self, node: int):
        def fit(msg: Message, ctxt: Context) -> Message:
            parameters = ndarrays_to_parameters([self.vectors[node]])
            fit = FitRes(Status(Code.OK, ""), parameters, 1, {})
            return Message(compat.fitres_to_recorddict(fit, keep_input=False), reply_to=msg)

        return fit


@pytest.mark.parametrize(
    "leaves",
    [
        {33: Stage.SETUP},  # killed between two rounds, still listed
        {33: Stage.SHARE_KEYS},
        {33: Stage.COLLECT_MASKED_VECTORS},  # killed while it trains
        {44: Stage.SETUP, 55: Stage.COLLECT_MASKED_VECTORS},
        {44: Stage.COLLECT_MASKED_VECTORS, 55: Stage.COLLECT_MASKED_VECTORS},
    ],
    ids=["setup", "share-keys", "collect", "setup-and-collect", "two-in-collect"],
)
def test_secaggplus_unmasks_the_sum_of_the_robots_left_whenever_others_leave(robot_process, leaves):
    """Flower's SecAgg+ on its own robot side (``secaggplus_mod``) for 3 robots (5 where two
    leave; threshold 2 in both): robots that leave before the unmask stage, in any stage, leave
    the sum of the others' vectors, within the quantisation (k x 2c/Q). Flower 1.42's own
    workflow fails where one leaves before it shares its keys (the survivors are asked for shares
    of its key they never got: "Not enough shares to recover secret"): the first, second and
    fourth cases (issue 50)."""
    secagg = load_config(FAST, [ON]).deploy.secagg
    nodes = (11, 22, 33, 44, 55) if 44 in leaves else (11, 22, 33)
    made = np.random.default_rng(5)
    vectors = {n: made.uniform(-0.5, 0.5, 40) for n in nodes}
    adapter = Adapter(None, list(nodes), 0)
    secure_sum(Loopback(vectors, leaves), adapter, 1, secagg, timeout=1)
    left = [n for n in nodes if n not in leaves]
    assert adapter.count == len(left)
    step = 2 * secagg.clipping_range / secagg.quantization_range
    error = np.abs(adapter.mean * adapter.count - sum(vectors[n] for n in left))
    assert error.max() < len(left) * step  # each value rounded by under one step


def test_a_sum_within_the_bound_whose_mean_has_a_negative_variance_is_refused():
    """Issue 50's fault sweep, case 1: an update within norm_bound moved a BatchNorm variance
    below 0 in the mean - every score NaN for the rest of a FINISHED run. A plain round
    refuses such an upload; under SecAgg+ the server refuses such a sum: here one robot's
    update moves a running variance by -400 (x 5 / 1000 in its vector), the mean by -77 (2000 /
    26 samples): within norm_bound=1000, below 0."""
    config = load_config(
        FAST, [ON, "method=FedAvg", "data.clients=3", "deploy.secagg.norm_bound=1000"]
    )
    secagg = config.deploy.secagg
    server = ServerSide(config)
    key = next(k for k in server.global_weights if k.endswith("running_var"))
    results = uploads(server, [5, 9, 12], 0.0)
    record = masked.message_settings(secagg, 0.0)
    vectors = [masked.robot_vector(r, server.global_weights, record)[0] for r in results]
    unpack(secagg_sum(vectors, secagg), 3, server, secagg)  # unchanged tensors: taken
    bad = dataclasses.replace(
        results[0],
        weights={**results[0].weights, key: results[0].weights[key] - 1000 / 5 * 2},
    )
    vectors[0] = masked.robot_vector(bad, server.global_weights, record)[0]
    with pytest.raises(ValueError, match=rf"it would make {key} a variance below 0 \(min -"):
        unpack(secagg_sum(vectors, secagg), 3, server, secagg)
