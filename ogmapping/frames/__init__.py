"""Frames and cameras: the conventions, rotations, torch geometry on them, preprocessing, which frames a run streams."""
