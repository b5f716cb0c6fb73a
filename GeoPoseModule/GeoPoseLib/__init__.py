"""Helpers of the GeoPose module that need neither Qt nor MRML (importable in any Python 3.9+)."""
