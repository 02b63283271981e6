"""Files the tests use as a user's own code and configs (a model defined outside the package)."""
