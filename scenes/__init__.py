"""quietframe.scenes."""
