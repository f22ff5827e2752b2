"""Map predictors: observed map in, ensemble of occupancy-probability maps out (SPEC §4)."""
