"""System identification: fitting the model's parameters to logged runs of an arm."""
