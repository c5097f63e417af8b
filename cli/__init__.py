"""Thin command front ends: parse arguments, call the library, print what was made."""
