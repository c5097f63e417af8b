"""Tests of dbb_capture.background."""
