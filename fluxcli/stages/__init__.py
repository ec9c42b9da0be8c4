"""One module per subcommand: ``run(config, ctx) -> artefact path``."""
