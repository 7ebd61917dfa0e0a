"""Shared fixtures. The throwaway PKI fixtures live in tests/pki_fixtures.py."""

pytest_plugins = ["tests.pki_fixtures"]
