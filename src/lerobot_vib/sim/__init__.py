"""ALOHA simulation: selective-rendering tasks and env, scripted demonstrations, the dataset recorder."""
