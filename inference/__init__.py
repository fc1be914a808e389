"""medseg inference stage (command-line entry point in `cli.py`)."""
