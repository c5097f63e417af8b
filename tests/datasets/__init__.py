"""Tests of dbb_capture.datasets."""
