"""Watching sessions as they map: renders and point clouds to Foxglove and into the recordings."""
