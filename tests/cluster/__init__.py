"""Cluster tests: a package, so that the package-scoped Ray session ends after the last of them."""
