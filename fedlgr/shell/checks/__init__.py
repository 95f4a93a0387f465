"""Input checks, in one place: what a command (or a robot receiving a config) checks
before the round's core runs - the rules of each config section (:mod:`.settings`) and
those across sections (:mod:`.experiment`), the generic value validators and the bounds a
method's settings declare (:mod:`.values`), paths and files (:mod:`.paths`), and tracking
stores and sweep storages (:mod:`.stores`). The core trusts the config it is given and
makes no such check."""
