/* factory.S - the built-in (factory) application inside firmware.elf: app.bin at EXEC_BASE
 * (mps2-boot.ld). FACTORY_BIN is its path, set by target.mk. */
    .section .factory, "a"
    .incbin FACTORY_BIN
