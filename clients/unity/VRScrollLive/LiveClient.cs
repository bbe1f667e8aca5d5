// The transport of the VRScroll live service (docs/live.md) for Unity and any .NET: the control channel
// over System.Net.WebSockets.ClientWebSocket, the pose and pen datagrams over System.Net.Sockets.UdpClient
// (binary, both ways: Datagrams.cs).
// Nothing beyond the .NET base library (compiles with Mono's mcs). Units as on the wire: mm, degrees,
// quaternions w first, in the service's right-handed frame (z up); converting from Unity's frame is the
// caller's (see VRScrollLiveDriver.cs).
//
// Threading: the control channel is received on a background task, the datagrams on a thread of their own; events
// and datagram replies are queued and read with TryGetEvent / TryGetPen, and the newest approximation is kept in
// LatestApproximation (the newest wins), its frame estimates (MSD, share within the thresholds; they follow it in
// their own datagram) in LatestEstimates, so a MonoBehaviour reads them from Update() without blocking.
using System;
using System.Collections.Concurrent;
using System.Collections.Generic;
using System.Diagnostics;
using System.Net;
using System.Net.Sockets;
using System.Net.WebSockets;
using System.Text;
using System.Threading;
using System.Threading.Tasks;

namespace VRScroll.Live
{
    public class LiveError : Exception
    {
        public LiveError(string message) : base(message) { }
    }

    public class LiveClient : IDisposable
    {
        public const int ProtocolVersion = 4;
        const int MaxQueued = 4096;

        readonly Uri url;
        readonly string role;
        readonly string token;
        readonly ClientWebSocket ws = new ClientWebSocket();
        readonly CancellationTokenSource stop = new CancellationTokenSource();
        readonly ConcurrentQueue<Dictionary<string, object>> events = new ConcurrentQueue<Dictionary<string, object>>();
        readonly ConcurrentQueue<Dictionary<string, object>> pens = new ConcurrentQueue<Dictionary<string, object>>();
        readonly SemaphoreSlim eventSignal = new SemaphoreSlim(0);
        readonly Stopwatch clock = Stopwatch.StartNew();
        UdpClient udp;
        IPEndPoint poseEndPoint;  // the worker's port (protocol 3): poses go there, pens to udp_port
        byte[] sessionBytes;  // the welcome's session, as samples carry it
        Task controlReceiver;
        Thread datagramReceiver;
        long poseSeq, penSeq;
        volatile Dictionary<string, object> latestApproximation;
        volatile Dictionary<string, object> latestEstimates;

        public Dictionary<string, object> Welcome { get; private set; }
        public string Session { get { return Welcome == null ? null : Welcome["session"] as string; } }
        public Dictionary<string, object> LatestApproximation { get { return latestApproximation; } }
        public Dictionary<string, object> LatestEstimates { get { return latestEstimates; } }
        public int ApproximationsReceived;
        public int EstimatesReceived;
        public int PensReceived;

        public LiveClient(Uri url, string role = "control", string token = null)
        {
            this.url = url;
            this.role = role;
            this.token = token;
        }

        /// Seconds on this client's clock: sent as t_s, echoed in replies (round trip = Now - t_s).
        public double Now { get { return clock.Elapsed.TotalSeconds; } }

        /// Connect, say hello, open the datagram socket; returns the welcome. LiveError if refused.
        public async Task<Dictionary<string, object>> ConnectAsync(double timeoutS = 10)
        {
            await ws.ConnectAsync(url, stop.Token);
            controlReceiver = ReceiveControl();
            var hello = new Dictionary<string, object> { { "type", "hello" }, { "protocol", ProtocolVersion }, { "role", role } };
            if (token != null) hello["token"] = token;
            await SendAsync(hello);
            Welcome = await ExpectAsync(timeoutS, "welcome");
            if (role == "control")
            {
                sessionBytes = Datagrams.SessionBytes(Session);
                udp = new UdpClient(url.Host == "localhost" ? "127.0.0.1" : url.Host, Convert.ToInt32(Welcome["udp_port"]));
                // every reply comes from udp_port (the connected address); poses are sent past it, to pose_port
                var service = (IPEndPoint)udp.Client.RemoteEndPoint;
                poseEndPoint = new IPEndPoint(service.Address, Convert.ToInt32(Welcome["pose_port"]));
                datagramReceiver = new Thread(ReceiveDatagrams) { IsBackground = true, Name = "VRScrollLive replies" };
                datagramReceiver.Start();
            }
            return Welcome;
        }

        // ---- control channel ---------------------------------------------------------------
        public Task SendAsync(Dictionary<string, object> message)
        {
            return SendTextAsync(Json.Write(message));
        }

        public Task SendTextAsync(string text)
        {
            var bytes = new ArraySegment<byte>(Encoding.UTF8.GetBytes(text));
            return ws.SendAsync(bytes, WebSocketMessageType.Text, true, stop.Token);
        }

        public Task SetTargetAsync(string shape)
        {
            return SendAsync(new Dictionary<string, object> { { "type", "target" }, { "shape", shape } });
        }

        public Task LockAsync()
        {
            return SendAsync(new Dictionary<string, object> { { "type", "lock" } });
        }

        public Task RequestStatusAsync()
        {
            return SendAsync(new Dictionary<string, object> { { "type", "status" } });
        }

        public bool TryGetEvent(out Dictionary<string, object> ev)
        {
            return events.TryDequeue(out ev);
        }

        /// The next event of one of `types`, skipping others; LiveError on an error about a control
        /// message (unless "error" is among the types), on the channel closing, or after timeoutS.
        public async Task<Dictionary<string, object>> ExpectAsync(double timeoutS, params string[] types)
        {
            var deadline = Now + timeoutS;
            while (true)
            {
                Dictionary<string, object> ev;
                while (events.TryDequeue(out ev))
                {
                    var type = ev["type"] as string;
                    if (Array.IndexOf(types, type) >= 0) return ev;
                    if (type == "closed" || (type == "error" && (ev["source"] as string) == "control"))
                        throw new LiveError(type + ": " + (ev.ContainsKey("code") ? ev["code"] + " " : "") + ev["message"]);
                }
                var left = deadline - Now;
                if (left <= 0) throw new LiveError("no " + string.Join(" or ", types) + " within " + timeoutS + " s");
                await eventSignal.WaitAsync(TimeSpan.FromSeconds(left));
            }
        }

        async Task ReceiveControl()
        {
            var buffer = new byte[1 << 16];
            var message = new List<byte>();
            string reason = "closed";
            try
            {
                while (ws.State == WebSocketState.Open)
                {
                    var result = await ws.ReceiveAsync(new ArraySegment<byte>(buffer), stop.Token);
                    if (result.MessageType == WebSocketMessageType.Close)
                    {
                        reason = result.CloseStatusDescription ?? "closed";
                        break;
                    }
                    for (int k = 0; k < result.Count; k++) message.Add(buffer[k]);
                    if (!result.EndOfMessage) continue;
                    Enqueue(events, Json.ParseObject(Encoding.UTF8.GetString(message.ToArray())));
                    message.Clear();
                    eventSignal.Release();
                }
            }
            catch (Exception e) when (e is WebSocketException || e is OperationCanceledException)
            {
                reason = e.Message;
            }
            Enqueue(events, new Dictionary<string, object> { { "type", "closed" }, { "message", reason } });
            eventSignal.Release();
        }

        // ---- datagrams ----------------------------------------------------------------------
        /// The tracked device pose (anchor): position mm, orientation w, x, y, z. Returns its seq.
        public long SendPose(double[] positionMm, double[] quatWxyz)
        {
            return SendSample(Datagrams.Pose, ref poseSeq, positionMm, quatWxyz, null, null);
        }

        /// A pen sample (tip mm, orientation w first), optionally with the device pose it was tracked with.
        public long SendPen(double[] positionMm, double[] quatWxyz, double[] devicePositionMm = null, double[] deviceQuatWxyz = null)
        {
            return SendSample(Datagrams.Pen, ref penSeq, positionMm, quatWxyz, devicePositionMm, deviceQuatWxyz);
        }

        /// Any bytes, to the port pens go to (udp_port), or with toPosePort to the one poses go to.
        public void SendRawDatagram(byte[] data, bool toPosePort = false)
        {
            if (toPosePort) udp.Client.SendTo(data, poseEndPoint);
            else udp.Send(data, data.Length);
        }

        long SendSample(byte kind, ref long seq, double[] position, double[] quat, double[] devicePosition, double[] deviceQuat)
        {
            SendRawDatagram(Datagrams.EncodeSample(kind, sessionBytes, seq, Now, position, quat, devicePosition, deviceQuat),
                            kind == Datagrams.Pose);
            return seq++;
        }

        public bool TryGetPen(out Dictionary<string, object> reply)
        {
            return pens.TryDequeue(out reply);
        }

        // The replies are read by a thread of their own, blocked in the socket's receive: a reply wakes it and nothing
        // else. Awaiting UdpClient.ReceiveAsync instead (until this change) woke Mono's socket-polling thread, which
        // handed the reply to a thread-pool thread, which ran the rest: two or three wake-ups per reply, each a wait for
        // a core on a busy machine (docs/live.md, "The clients' waits").
        void ReceiveDatagrams()
        {
            var buffer = new byte[1 << 16];  // the largest datagram
            try
            {
                while (!stop.IsCancellationRequested)
                {
                    int n = udp.Client.Receive(buffer);
                    double received = Now;  // stamped before parsing: the round trip is the transport's and the service's
                    Dictionary<string, object> reply;
                    try
                    {
                        reply = Datagrams.DecodeReply(buffer, n);
                    }
                    catch (FormatException)
                    {
                        continue;  // not a reply of this protocol: skipped
                    }
                    reply["received_s"] = received;
                    var type = reply["type"] as string;
                    if (type == "approximation")
                    {
                        latestApproximation = reply;
                        Interlocked.Increment(ref ApproximationsReceived);
                    }
                    else if (type == "estimates")
                    {
                        latestEstimates = reply;
                        Interlocked.Increment(ref EstimatesReceived);
                    }
                    else
                    {
                        Enqueue(pens, reply);
                        Interlocked.Increment(ref PensReceived);
                    }
                }
            }
            catch (Exception e) when (e is ObjectDisposedException || e is SocketException)
            {
                // the socket was closed: stop receiving
            }
        }

        static void Enqueue(ConcurrentQueue<Dictionary<string, object>> queue, Dictionary<string, object> item)
        {
            Dictionary<string, object> dropped;
            while (queue.Count >= MaxQueued) queue.TryDequeue(out dropped);
            queue.Enqueue(item);
        }

        /// Close the control channel (the receiver ends when the service answers the close) and the socket.
        public async Task CloseAsync()
        {
            if (ws.State == WebSocketState.Open)
                await ws.CloseOutputAsync(WebSocketCloseStatus.NormalClosure, "bye", CancellationToken.None);
            if (controlReceiver != null) await controlReceiver;
            Dispose();
            if (datagramReceiver != null) datagramReceiver.Join();
        }

        public void Dispose()
        {
            stop.Cancel();
            if (udp != null) udp.Close();
            ws.Dispose();
        }
    }
}
