from relocdepth.cli.main import main

main()
