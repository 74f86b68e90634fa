"""quietframe.bench."""
