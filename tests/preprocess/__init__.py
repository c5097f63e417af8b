"""Tests of dbb_capture.preprocess."""
