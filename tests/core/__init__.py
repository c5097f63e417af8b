"""Tests of dbb_capture.core."""
