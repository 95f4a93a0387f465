"""Federated training: a map of the package.

Where code runs:

- ``client/``: what runs on a robot - local training, the plugin hooks, the side that
  answers the server's messages, clients side by side (threads) or stacked.
- ``server/``: what runs on the aggregating machine - the global tensors, aggregation,
  the server's evaluation.
- ``strategies/``: the aggregation strategies (FedAvg, FedBN, FedProx, ...), one module
  each, with a server half and a client half (plugins); registered in ``fedlgr.core.methods``
  with the continual-learning methods (``fedlgr.core.continual``).

What both sides share: ``messages`` (the only boundary: what the server and the clients
say to each other in a round), ``scope`` (the model and which of its tensors are
exchanged), ``records`` (what a round records: results.csv columns, MLflow keys) and
``evaluation`` (scoring a model on the test scenes).

Running an experiment: ``experiment`` (``run_experiment``: Fabric set-up, processes),
the round loop over a runtime's rounds, ``in_process`` (both sides in this process or
in Fabric's processes; the Flower runtime is ``fedlgr.shell.deploy.flower``), ``resume``
(checkpoints and ``--resume``) and ``result`` (what a run returns and prints).
"""
