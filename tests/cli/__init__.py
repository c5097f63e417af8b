"""Tests of dbb_capture.cli."""
