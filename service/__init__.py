"""quietframe.service."""
