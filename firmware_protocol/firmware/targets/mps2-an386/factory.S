/* factory.S - the built-in (factory) application inside firmware.elf: app.bin at EXEC_BASE
 * (mps2-boot.ld). FACTORY_BIN is its path, set by target.mk. */
    .section .factory, "a"
    .incbin FACTORY_BIN
/* the execution region's header sector: zeros, no image header: the built-in image is what
 * the region holds (the boot stage copies a slot over it when one is chosen) */
    .section .factory_header, "a"
    .space 96
