"""Tests of dbb_capture.crops."""
