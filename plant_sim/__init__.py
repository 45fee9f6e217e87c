"""plant_sim package."""
