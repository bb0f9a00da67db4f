"""bioscara-gym: the Bioscara SCARA arm as a reinforcement-learning testbed."""
