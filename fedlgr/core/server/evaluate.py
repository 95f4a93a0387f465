"""Server-side (centralised) evaluation, ``federated.server_eval``: the aggregated global
model scored on the test scenes by the server, every round and once before round 1.

The standard FL feature (Flower's ``evaluate_fn``) that the paper's full-model baselines
had and its FedRoot variants did not (there is no global top): the authors' Table III/IV
CPU figures include it (docs/methods.md, "Table III and IV: what the paper measured"). Scores are
logged as ``server/test/{loss,rmse,pcc}`` - over every task seen so far - and, with
tasks, ``server/task/<name>/...`` per task. A shared subset of the model (FedBN keeps its
batch-norm layers on the clients) is scored with the initial model's other tensors.
"""

from __future__ import annotations

from collections.abc import Callable

from fedlgr.core.evaluation import EvalSet, predict
from fedlgr.core.messages import RoundPlan, Weights
from fedlgr.core.meters.costs import Usage, measure
from fedlgr.core.meters.scores import regression_scores
from fedlgr.core.scope import initial_scholar


class ServerEvaluation:
    """Scores the global weights on ``test``, the scenes the clients score on."""

    def __init__(self, config, test: EvalSet):
        self.config, self.test = config, test
        self.model = initial_scholar(config).to(test.test_inputs.device)

    def scores(self, weights: Weights, task: int) -> dict[str, float]:
        cfg, test = self.config.train, self.test
        self.model.load_state_dict(weights, strict=False)
        pred = predict(self.model, test.test_inputs, cfg.eval_batch_size, test.autocast)
        compat = cfg.compat_batch_metrics
        seen, task_rows = test.rows(task, compat)
        out = regression_scores(pred[seen], test.test_targets[seen], compat).figures("server/test")
        for name, rows in task_rows.items():
            scores = regression_scores(pred[rows], test.test_targets[rows], compat)
            out |= scores.figures(f"server/task/{name}")
        return out


def serve_round(
    server,
    evaluation: ServerEvaluation | None,
    plan: RoundPlan,
    aggregate: Callable[[], dict[str, float] | None],
) -> tuple[dict[str, float], dict[str, float]]:
    """The server's part of round ``plan``: ``aggregate()`` (aggregation and the server
    update of ``server``, a :class:`ServerSide`; it may return figures of its own,
    SecAgg's), then its evaluation - and, in round 1, that of the initial model first.
    Returns the round's server figures (``cost/server_*``, ``server/...``, ``privacy/*``
    under DP, then aggregate's) and the initial model's scores (or {})."""
    device = next(iter(server.global_weights.values())).device
    before, initial = Usage(), {}
    if evaluation is not None and plan.round == 1:
        with measure(device) as before:
            initial = evaluation.scores(server.global_weights, plan.task)
    with measure(device) as usage:
        own = aggregate() or {}
        scores = evaluation.scores(server.global_weights, plan.task) if evaluation else {}
    cost = {
        "cost/server_cpu_s": usage.cpu_s + before.cpu_s,
        "cost/server_wall_s": usage.wall_s + before.wall_s,
    }
    privacy = {} if server.privacy is None else server.privacy.figures()
    return cost | scores | privacy | own, initial
