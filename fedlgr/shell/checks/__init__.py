"""Input checks a command (or a robot receiving a config) makes before the round's core runs: the
config against this machine (:mod:`.experiment`), paths (:mod:`.paths`), tracking stores and sweep
storages (:mod:`.stores`), the address-space limit. The core trusts the config it is given."""
