"""The round's core: what a federated round is, whatever runs it.

It imports nothing from :mod:`fedlgr.shell` (checked by import-linter, ``pyproject.toml``)
and trusts the config it is given: the shell checks it first.

Where code runs:

- ``client/``: what runs where the clients are (each on its own machine in the Flower
  runtime) - local training, the plug-in hooks, the side that answers the server's
  messages, clients side by side (threads) or stacked.
- ``server/``: what runs on the aggregating machine - the global tensors, aggregation,
  the choice of each round's clients, the server's evaluation.
- ``strategies/``: the aggregation strategies (FedAvg, FedBN, FedProx, SCAFFOLD, ...), one
  module each, with a server half and a client half (plug-ins); ``continual/``: the
  continual-learning methods (EWC, SI, MAS, LwF, rehearsal, FedLGR's replay), plug-ins
  that compose with every strategy. Both are registered in ``methods`` with their settings.

What both sides share: ``messages`` (the only boundary: what the server and the clients
say to each other in a round, weights and a strategy's payload), ``scope`` (the model and
which of its tensors are exchanged), ``metrics`` (every score and cost, by name),
``records`` (a round's figures as a table keyed by those names), ``evaluation`` (scoring a
model on the test scenes), ``meters`` (how scores and costs are measured), ``models``,
``data`` (the scenes' columns, augmentation), ``schedule`` and ``forgetting`` (tasks and
what is forgotten of them), ``state`` (what is kept between rounds; the generators).

Running rounds: ``rounds`` is what any runtime supplies to a run (its rounds and their
state); ``in_process`` is the in-process runtime (``Orchestrator``: clients in this
process or in Fabric's processes). The Flower runtime, and the run around any runtime
(tracking, checkpoints, resume), are the shell's.
"""
