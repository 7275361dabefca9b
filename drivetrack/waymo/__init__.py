"""Waymo Open Dataset v2 (perception, parquet): schema, reader and range-image geometry."""
