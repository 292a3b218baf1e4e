"""Scoring a map: the evaluation loop over streamed and held-out views, its metrics and LPIPS's weights."""
