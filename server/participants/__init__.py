"""Participants: anonymous sessions, their trials and votes, and every query of them."""
