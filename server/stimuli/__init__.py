"""Stimulus sets: what a study shows (its clips with their metrics, the videos, the character, the render
settings), immutable and content-addressed; a study's set is pinned when it opens (see docs/stimulus-sets.md)."""
