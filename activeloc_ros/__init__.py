"""Active action localization with predictive learning and reactive control."""
