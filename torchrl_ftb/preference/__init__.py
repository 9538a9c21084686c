"""preference stage."""
