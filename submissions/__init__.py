"""submissions package (see DESIGN.md)."""
