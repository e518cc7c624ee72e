"""scr_env."""
