"""can_db package."""
