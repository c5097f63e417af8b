"""Tests of dbb_capture.synth."""
