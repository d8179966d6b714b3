"""Researcher accounts and their bearer tokens."""
