"""Server-side (centralised) evaluation, ``federated.server_eval``: the aggregated global
model scored on the test scenes by the server, every round and once before round 1.

The standard FL feature (Flower's ``evaluate_fn``) that the paper's full-model baselines
had and its FedRoot variants did not (there is no global top): the authors' Table III/IV
CPU figures include it (README, "Table III and IV: what the paper measured"). Scores are
logged as ``server/test/{loss,rmse,pcc}`` - over every task seen so far - and, with
tasks, ``server/task/<name>/...`` per task. A shared subset of the model (FedBN keeps its
batch-norm layers on the clients) is scored with the initial model's other tensors.
"""

from __future__ import annotations

from fedlgr.federated.evaluation import predict
from fedlgr.federated.messages import Weights
from fedlgr.federated.scope import initial_scholar
from fedlgr.tracking.metrics import regression_scores


class ServerEvaluation:
    """Scores the global weights on ``test``'s scenes: an object with ``test_inputs``,
    ``test_targets``, ``seen_rows`` (per task: the rows of every task seen so far),
    ``test_rows`` (each task's rows) and ``autocast`` - the in-process clients' test set,
    the same scenes the clients score on."""

    def __init__(self, config, test):
        self.config, self.test = config, test
        self.model = initial_scholar(config).to(test.test_inputs.device)

    def scores(self, weights: Weights, task: int) -> dict[str, float]:
        cfg, test = self.config.train, self.test
        self.model.load_state_dict(weights, strict=False)
        pred = predict(self.model, test.test_inputs, cfg.eval_batch_size, test.autocast)
        compat = cfg.compat_batch_metrics
        seen = test.seen_rows[task]
        out = _named("server/test", regression_scores(pred[seen], test.test_targets[seen], compat))
        for name, rows in test.test_rows.items():
            scores = regression_scores(pred[rows], test.test_targets[rows], compat)
            out |= _named(f"server/task/{name}", scores)
        return out


def _named(prefix: str, scores) -> dict[str, float]:
    return {
        f"{prefix}/loss": scores.loss,
        f"{prefix}/rmse": scores.mean_rmse,
        f"{prefix}/pcc": scores.mean_pcc,
    }
