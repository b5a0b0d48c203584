#!/usr/bin/env python3
"""A TCP relay that delays every byte by a fixed time each way: a long round trip between a
`shoal client` and its `shoal serve` on one host, where `tc netem` is not available (this
project's machines have no `sch_netem`). Packet loss cannot be made in user space under TCP;
this relay does not try.

    python3 benches/net_relay.py LISTEN_PORT UPSTREAM_PORT ONE_WAY_MS

then `shoal client --connect tcp/127.0.0.1:LISTEN_PORT ...` with the server on UPSTREAM_PORT.
"""
import asyncio
import sys


async def pump(reader, writer, delay_s):
    loop = asyncio.get_running_loop()
    queue = asyncio.Queue()

    async def send():
        while True:
            due, data = await queue.get()
            if data is None:
                break
            wait = due - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
        writer.close()

    sender = asyncio.create_task(send())
    try:
        while True:
            data = await reader.read(65536)
            if not data:
                break
            await queue.put((loop.time() + delay_s, data))
    except ConnectionError:
        pass
    await queue.put((0, None))
    try:
        await sender
    except ConnectionError:
        pass


async def main():
    listen, upstream, one_way_ms = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
    delay_s = one_way_ms / 1000.0

    async def handle(c_reader, c_writer):
        try:
            s_reader, s_writer = await asyncio.open_connection("127.0.0.1", upstream)
        except OSError:
            c_writer.close()
            return
        await asyncio.gather(
            pump(c_reader, s_writer, delay_s), pump(s_reader, c_writer, delay_s)
        )

    server = await asyncio.start_server(handle, "127.0.0.1", listen)
    print(f"relay 127.0.0.1:{listen} -> 127.0.0.1:{upstream}, {one_way_ms} ms each way",
          flush=True)
    async with server:
        await server.serve_forever()


if __name__ == "__main__":
    asyncio.run(main())
