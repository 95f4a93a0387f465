"""fedlgr on Flower's Deployment Runtime: a SuperLink (the server), one SuperNode per
robot, and ``flwr run`` of the app in ``APP_DIR``.

* ``server_app.py`` - the ServerApp: the schedule, aggregation and MLflow logging, on the
  SuperLink's machine.
* ``nodes.py`` - which of the SuperLink's nodes take part in a run (the roster's robots),
  for the ServerApp.
* ``client_app.py`` - the ClientApp: a robot's data, model and private state, on its
  SuperNode's machine.
* ``wire.py`` - the round messages as Flower records.

docs/deployment.md has the commands.
"""

from pathlib import Path

APP_DIR = Path(__file__).parent / "app"  # the Flower app (pyproject.toml) for `flwr run`
