"""Running fedlgr's methods on real robots: the Flower apps (``fedlgr.deploy.flower``) and
what a deployment needs around them (TLS certificates, SuperNode keys: ``fedlgr deploy``)."""


def check_deployable(config) -> None:
    """What the Flower runtime does not do yet, refused before a run is submitted."""
    from fedlgr.errors import FedlgrError

    if config.federated.server_evaluates:
        raise FedlgrError(
            f"federated.server_eval={config.federated.server_eval}: not in the Flower runtime "
            "yet (its ServerApp holds no test scenes); use it with fedlgr run, or set it off"
        )
