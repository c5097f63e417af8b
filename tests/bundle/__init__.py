"""Tests of dbb_capture.bundle."""
