"""Alembic migrations of the SQL index; applied by storage.db.upgrade."""
