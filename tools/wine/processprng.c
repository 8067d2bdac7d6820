/* A stand-in for bcryptprimitives.dll, which Wine 8 lacks and Windows 10/11 has: Rust-built wheels
   (jsonschema-rs, rpds-py, pydantic-core...) import ProcessPrng from it. It forwards to RtlGenRandom
   (advapi32's SystemFunction036), which Wine has. Built with MinGW by tools/wine/wine.sh. */
#include <windows.h>

BOOLEAN WINAPI SystemFunction036(PVOID buffer, ULONG length);

BOOL WINAPI ProcessPrng(PBYTE data, SIZE_T length)
{
    while (length > 0) {
        ULONG chunk = length > 0x10000000 ? 0x10000000 : (ULONG)length;
        if (!SystemFunction036(data, chunk))
            return FALSE;
        data += chunk;
        length -= chunk;
    }
    return TRUE;
}
