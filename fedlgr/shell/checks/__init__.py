"""Input checks made before the round's core runs (which trusts the config it is given): the config
against this machine, paths, tracking stores and sweep storages, the address-space limit."""
