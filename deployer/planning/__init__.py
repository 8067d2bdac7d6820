"""Planning: the plan model, the planner, the plan file and the wire cost."""
