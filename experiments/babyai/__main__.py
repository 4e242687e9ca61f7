"""BabyAI GoTo levels measured in minigrid: `python -m experiments.babyai --help`."""
if __name__ == "__main__":
    from experiments.babyai.cli import main

    main()
