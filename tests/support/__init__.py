"""Test-only helpers that are not tests themselves."""
