"""quietframe.runtime."""
