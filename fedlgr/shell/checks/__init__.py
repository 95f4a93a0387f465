"""Input checks, in one place: what a command (or a robot receiving a config) checks
before the round's core runs - the values of settings (:mod:`.values`), paths and files
(:mod:`.paths`) and tracking and sweep stores (:mod:`.stores`). The core trusts the config
it is given and makes no such check."""
