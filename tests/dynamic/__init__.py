"""Tests of dbb_capture.dynamic: settings and presets, networks, the model and its losses, training,
the run-time stepper, evaluation and the run folder."""
