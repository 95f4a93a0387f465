"""The shell: everything around the round's core (:mod:`fedlgr.core`) that a researcher
drives it with.

- ``cli/``: the ``fedlgr`` commands, each declaring its own options.
- ``config/``: experiment configs - loading, layering, written out; ``checks/``: every
  check of a setting, a path or a store, made before the core runs.
- ``run/``: a run's life - the experiment (Fabric, processes), tracking each round,
  checkpoints, resume, owner locks, the result it prints.
- ``tracking/``: MLflow - stores, experiments, runs, the shared view; ``report/``: tables
  and plots of finished runs; ``sweep/``: Optuna sweeps.
- ``deploy/``: real robots - Flower's server and client apps, the roster, credentials.
- ``data/``: reading scenes and images, splitting them across clients, the synthetic
  living room; ``pretrain``, ``machine`` (threads, the allocator), ``console``,
  ``signals``.

The shell imports the core; the core never imports the shell. docs/development.md says
where new code goes.
"""
