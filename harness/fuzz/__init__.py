"""``rhonn-bench fuzz``: seeded and property-based fuzzing of the decoder, monitor, node and
controllers.
"""
