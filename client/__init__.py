"""quietframe.client."""
