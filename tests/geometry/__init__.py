"""Tests of dbb_capture.geometry."""
