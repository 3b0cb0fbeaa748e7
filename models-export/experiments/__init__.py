"""Experiments built on the trainer's library (posefuse_train): the paper's ablation, the
camera backbone study, breakdowns by range and by heading error, and the RESULTS.md renderer.
The library never imports this package."""
