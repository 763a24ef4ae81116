from pcfbench.entry import main

main()
