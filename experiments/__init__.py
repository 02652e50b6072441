"""usmswitch.experiments: the paper's experiments, one module each, and the report beside the paper.

Run them with `usmswitch-experiment` (`cli.py`; docs/experiments.md). By default each runs on the
simulated rig in virtual time, in this process, through the daemon's own loop, predictor and
records code (`rig.SimulatedRig`); `--socket` runs on a live daemon, `--from-records` analyses a
records file. The daemon never imports this package.
"""
