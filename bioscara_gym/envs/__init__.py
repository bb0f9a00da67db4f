"""Gymnasium tasks of the Bioscara arm."""
