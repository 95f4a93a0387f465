"""fedlgr: federated continual learning of socially appropriate robot behaviours."""

__version__ = "0.1.0"
