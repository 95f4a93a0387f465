"""Running fedlgr's methods on real robots: the Flower apps (``fedlgr.shell.deploy.flower``) and
what a deployment needs around them (TLS certificates, SuperNode keys: ``fedlgr deploy``)."""
