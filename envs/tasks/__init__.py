"""The 11 DISCOVERSE tasks, one module each."""
