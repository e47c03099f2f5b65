"""render/backends."""
