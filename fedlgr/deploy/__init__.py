"""Running fedlgr's methods on real robots: the Flower apps (``fedlgr.deploy.flower``) and
what a deployment needs around them (TLS certificates, SuperNode keys: ``fedlgr deploy``)."""
