"""fedlgr: federated continual learning of socially appropriate robot behaviours.

Two layers: :mod:`fedlgr.core`, the round's core (messages, strategies, scope, plug-ins,
continual methods, models, meters), and :mod:`fedlgr.shell` around it (commands, configs
and their checks, a run's life, tracking, sweeps, reports, deployment). The core imports
nothing from the shell; :mod:`fedlgr.errors` is shared by both.
"""

__version__ = "0.1.0"
