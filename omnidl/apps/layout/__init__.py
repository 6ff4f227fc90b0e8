"""Layout studies (thesis ch. 5): the analytic room simulator, the acceptance tables and the noise study."""
