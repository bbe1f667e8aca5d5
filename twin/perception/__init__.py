"""Perception: the redirection thresholds and detection rule (models/perception/perception.toml) and
psychometric fitting of redirection trials.

May import `twin.device` and `twin.formats` only.
"""
