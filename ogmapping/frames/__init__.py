"""Frames and cameras: the conventions, torch geometry on them, preprocessing, which frames a run streams."""
