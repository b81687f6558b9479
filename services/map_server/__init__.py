"""The map server: durable store, in-memory fleet map, Zenoh ingest and HTTP."""
