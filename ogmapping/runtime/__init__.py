"""How the engine runs on its machine: the execution profile, torch threads, memory, device constants, frame budgets."""
