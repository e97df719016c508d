"""Outputs: CSV, HTML report, certificate, JUnit properties; all written atomically by the controller."""
