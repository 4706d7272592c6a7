"""Thin Zenoh adapters around the vergence library: one module per process, each with main(...)."""
