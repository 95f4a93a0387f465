"""The shell: everything around the round's core (:mod:`fedlgr.core`) that a researcher drives it
with - commands, configs and checks, runs, tracking, reports, sweeps, robots, data. The shell
imports the core, never the reverse; docs/development.md says where new code goes."""
