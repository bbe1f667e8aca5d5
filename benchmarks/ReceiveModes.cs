// Two ways a .NET client can wait for a datagram's reply, alternated every half second against one echo process
// (benchmarks/bench_loopback.py --csharp runs it):
//   mono ReceiveModes.exe PORT SECONDS HZ
// "async": a loop awaiting UdpClient.ReceiveAsync (the live C# client until issue 40's sixth round); "thread": a
// thread of its own blocked in Socket.Receive (the client since). Each sends HZ datagrams a second on its own socket
// (its send time inside) and stamps each echo as it is received. Prints one line per mode: round trip p50 / p99 /
// max ms and the count.
using System;
using System.Collections.Generic;
using System.Diagnostics;
using System.Net;
using System.Net.Sockets;
using System.Threading;
using System.Threading.Tasks;

static class ReceiveModes
{
    static readonly Stopwatch Clock = Stopwatch.StartNew();
    static double Now { get { return Clock.Elapsed.TotalSeconds; } }

    static void Record(List<double> into, byte[] data)
    {
        double sent = BitConverter.ToDouble(data, 0);
        lock (into) into.Add(1e3 * (Now - sent));
    }

    static async Task ReceiveAsyncLoop(UdpClient udp, List<double> into)
    {
        try
        {
            while (true) Record(into, (await udp.ReceiveAsync()).Buffer);
        }
        catch (Exception e) when (e is ObjectDisposedException || e is SocketException) { }
    }

    static void ReceiveThread(UdpClient udp, List<double> into)
    {
        var buffer = new byte[1 << 16];
        try
        {
            while (true)
            {
                udp.Client.Receive(buffer);
                Record(into, buffer);
            }
        }
        catch (Exception e) when (e is ObjectDisposedException || e is SocketException) { }
    }

    static string Line(string mode, List<double> values)
    {
        values.Sort();
        if (values.Count == 0) return mode + ": no replies";
        Func<double, double> at = q => values[(int)Math.Min(values.Count - 1, Math.Round(q / 100.0 * (values.Count - 1)))];
        return string.Format("{0}: p50 {1:F3} / p99 {2:F3} / max {3:F3} ms over {4}", mode, at(50), at(99),
                             values[values.Count - 1], values.Count);
    }

    static int Main(string[] args)
    {
        int port = int.Parse(args[0]);
        double seconds = double.Parse(args[1]), hz = double.Parse(args[2]);
        var asyncUdp = new UdpClient("127.0.0.1", port);
        var threadUdp = new UdpClient("127.0.0.1", port);
        var asyncTimes = new List<double>();
        var threadTimes = new List<double>();
        var asyncLoop = ReceiveAsyncLoop(asyncUdp, asyncTimes);  // runs on Mono's threads until the socket closes
        var thread = new Thread(() => ReceiveThread(threadUdp, threadTimes)) { IsBackground = true };
        thread.Start();
        var payload = new byte[104];
        long sent = 0;
        double start = Now;
        while (Now - start < seconds)
        {
            var udp = ((int)((Now - start) / 0.5)) % 2 == 0 ? asyncUdp : threadUdp;
            Buffer.BlockCopy(BitConverter.GetBytes(Now), 0, payload, 0, 8);
            udp.Send(payload, payload.Length);
            sent++;
            double wait = start + sent / hz - Now;
            if (wait > 0) Thread.Sleep(TimeSpan.FromSeconds(wait));
        }
        Thread.Sleep(100);
        asyncUdp.Close();
        threadUdp.Close();
        asyncLoop.Wait(1000);
        thread.Join(1000);
        Console.WriteLine(Line("async", asyncTimes));
        Console.WriteLine(Line("thread", threadTimes));
        return 0;
    }
}
