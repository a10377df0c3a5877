"""agents package (see DESIGN.md)."""
