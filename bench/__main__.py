from pcfbench.cli import main

main()
