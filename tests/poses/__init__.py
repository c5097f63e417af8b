"""Tests of dbb_capture.poses."""
