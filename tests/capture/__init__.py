"""Tests of dbb_capture.capture."""
