"""The shell around the round's core (:mod:`fedlgr.core`): commands, configs and checks, runs,
tracking, reports, sweeps, robots, data. It imports the core, never the reverse."""
