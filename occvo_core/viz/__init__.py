"""Views of a run (optional extras; nothing here is imported unless a view is asked for)."""
