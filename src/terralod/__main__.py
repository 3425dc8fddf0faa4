from terralod.cli import main

main()
