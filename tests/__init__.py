"""The test suite of davis_rig (a package, so that :mod:`tests.helpers` imports by name)."""
