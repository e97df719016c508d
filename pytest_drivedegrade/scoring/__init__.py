"""Scoring: per-frame planning metrics and the scores built on them."""
