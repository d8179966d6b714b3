"""Participants: anonymous sessions, their trials and votes."""
