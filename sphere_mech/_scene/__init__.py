"""Scenes: a mechanical system assembled from exactly the effects it lists."""
