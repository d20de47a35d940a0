"""Schemas of the run configuration (pydantic), checked once when a job starts (`src/schema/run.py`)."""
