// A scripted session against a running `vrscroll serve`, through the C# transport alone (no Unity):
//   mono ScriptedSession.exe ws://127.0.0.1:PORT SHAPE [SECONDS]
// hello; a malformed and an out-of-order message (each must get an error, the channel staying open);
// target; poses at 90 Hz until approximations come back; lock; gate, progress, done; then pen samples
// touching the root flap, each of which must come back redirected. Prints one JSON line of what it saw
// and exits 0 when every step held, 1 otherwise. With SECONDS: then pens at ~360 Hz and poses at a quarter of
// that for SECONDS, and the round trips this client measured (send to receive, its own clock), p50 and p99 ms:
// benchmarks/bench_live.py --csharp runs it.
using System;
using System.Collections.Generic;
using System.Threading;
using System.Threading.Tasks;
using VRScroll.Live;

static class ScriptedSession
{
    static double[] Rotate(double[] q, double[] v)
    {
        // v rotated by the unit quaternion q = (w, x, y, z)
        double w = q[0], x = q[1], y = q[2], z = q[3];
        double tx = 2 * (y * v[2] - z * v[1]), ty = 2 * (z * v[0] - x * v[2]), tz = 2 * (x * v[1] - y * v[0]);
        return new[] { v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz), v[2] + w * tz + (x * ty - y * tx) };
    }

    static double Percentile(List<double> values, double q)
    {
        if (values.Count == 0) return double.NaN;
        var sorted = new List<double>(values);
        sorted.Sort();
        double at = q / 100.0 * (sorted.Count - 1);
        int below = (int)Math.Floor(at);
        int above = Math.Min(below + 1, sorted.Count - 1);
        return sorted[below] + (sorted[above] - sorted[below]) * (at - below);
    }

    static double RoundTripMs(Dictionary<string, object> reply)
    {
        return 1e3 * (Convert.ToDouble(reply["received_s"]) - Convert.ToDouble(reply["t_s"]));
    }

    /// Pens at ~360 Hz (and a pose every fourth) for `seconds`; the round trips of the replies, ms.
    static async Task Measure(LiveClient client, double seconds, double[] root, double[] quat, Dictionary<string, object> seen)
    {
        var pens = new List<double>();
        var poses = new List<double>();
        Dictionary<string, object> reply;
        while (client.TryGetPen(out reply)) { }
        long lastApproximation = -1;
        int sent = 0;
        var clock = System.Diagnostics.Stopwatch.StartNew();
        while (clock.Elapsed.TotalSeconds < seconds)
        {
            var local = new[] { -10.0 + 20.0 * (sent % 40) / 39.0, -50.0 + 100.0 * (sent % 40) / 39.0, 0.0 };
            var offset = Rotate(quat, local);
            client.SendPen(new[] { root[0] + offset[0], root[1] + offset[1], root[2] + offset[2] }, quat);
            if (++sent % 4 == 0) client.SendPose(root, quat);
            while (client.TryGetPen(out reply)) pens.Add(RoundTripMs(reply));
            var latest = client.LatestApproximation;
            if (latest != null && Convert.ToInt64(latest["seq"]) != lastApproximation)
            {
                lastApproximation = Convert.ToInt64(latest["seq"]);
                poses.Add(RoundTripMs(latest));
            }
            double wait = sent / 360.0 - clock.Elapsed.TotalSeconds;
            if (wait > 0) await Task.Delay(TimeSpan.FromSeconds(wait));
        }
        await Task.Delay(100);
        while (client.TryGetPen(out reply)) pens.Add(RoundTripMs(reply));
        seen["measure_pens_sent"] = sent;
        seen["measure_pen_ms"] = new object[] { Percentile(pens, 50), Percentile(pens, 99), pens.Count };
        seen["measure_pose_ms"] = new object[] { Percentile(poses, 50), Percentile(poses, 99), poses.Count };
    }

    static async Task<Dictionary<string, object>> Run(Uri url, string shape, double seconds)
    {
        var seen = new Dictionary<string, object>();
        using (var client = new LiveClient(url))
        {
            var welcome = await client.ConnectAsync();
            seen["welcome_role"] = welcome["role"];

            await client.SendTextAsync("{\"type\": \"lock\"");  // not JSON
            seen["malformed_error"] = (await client.ExpectAsync(5, "error"))["code"];
            await client.LockAsync();  // nothing approximated yet
            seen["out_of_order_error"] = (await client.ExpectAsync(5, "error"))["code"];

            await client.SetTargetAsync(shape);
            seen["target"] = ((Dictionary<string, object>)(await client.ExpectAsync(60, "target_ready"))["target"])["name"];

            var position = new[] { 10.0, 0.0, 190.0 };
            var level = new[] { 1.0, 0.0, 0.0, 0.0 };
            var start = DateTime.UtcNow;
            long lastPose = -1;
            while ((client.ApproximationsReceived < 20 || client.EstimatesReceived < 10) && (DateTime.UtcNow - start).TotalSeconds < 10)
            {
                lastPose = client.SendPose(position, level);
                await Task.Delay(11);
            }
            await Task.Delay(100);
            var approximation = client.LatestApproximation;
            seen["approximations"] = client.ApproximationsReceived;
            seen["estimates"] = client.EstimatesReceived;
            var estimates = client.LatestEstimates;
            seen["estimates_answer_an_approximation"] = estimates != null && Convert.ToInt64(estimates["seq"]) <= lastPose;
            seen["msd_estimate_mm"] = estimates == null ? null : estimates["msd_estimate_mm"];
            seen["poses_sent"] = lastPose + 1;

            await client.LockAsync();
            var locked = await client.ExpectAsync(5, "locked");
            seen["gate_passed"] = (await client.ExpectAsync(10, "gate"))["passed"];
            seen["progress_source"] = (await client.ExpectAsync(10, "progress"))["source"];
            var outcome = await client.ExpectAsync(15, "done", "refused", "stopped");
            seen["outcome"] = outcome["type"];
            if ((string)outcome["type"] != "done") return seen;
            seen["share_within"] = ((Dictionary<string, object>)outcome["redirection"])["share_within"];

            // pens touching the root flap (flat around the anchor): along its x and y, 40 samples at 360 Hz
            var root = Json.Numbers(locked["root_position_mm"]);
            var quat = Json.Numbers(locked["root_quat_wxyz"]);
            var pens = 40;
            for (int k = 0; k < pens; k++)
            {
                var local = new[] { -10.0 + 20.0 * k / (pens - 1), -50.0 + 100.0 * k / (pens - 1), 0.0 };
                var offset = Rotate(quat, local);
                client.SendPen(new[] { root[0] + offset[0], root[1] + offset[1], root[2] + offset[2] }, quat);
                await Task.Delay(3);
            }
            var deadline = DateTime.UtcNow.AddSeconds(2);
            var answered = new HashSet<long>();
            double largestOffset = 0, largestRoundTripMs = 0;
            while (answered.Count < pens && DateTime.UtcNow < deadline)
            {
                Dictionary<string, object> reply;
                if (!client.TryGetPen(out reply)) { await Task.Delay(5); continue; }
                answered.Add(Convert.ToInt64(reply["seq"]));
                largestOffset = Math.Max(largestOffset, Convert.ToDouble(reply["offset_mm"]));
                largestRoundTripMs = Math.Max(largestRoundTripMs, 1e3 * (Convert.ToDouble(reply["received_s"]) - Convert.ToDouble(reply["t_s"])));
            }
            seen["pens_sent"] = pens;
            seen["pens_redirected"] = answered.Count;
            seen["largest_offset_mm"] = largestOffset;
            seen["largest_pen_round_trip_ms"] = largestRoundTripMs;

            if (seconds > 0) await Measure(client, seconds, root, quat, seen);

            await client.RequestStatusAsync();
            seen["status_state"] = (await client.ExpectAsync(5, "status"))["state"];
            await client.CloseAsync();
        }
        return seen;
    }

    static int Main(string[] args)
    {
        double seconds = 0;
        if (args.Length < 2 || args.Length > 3 || (args.Length == 3 && !double.TryParse(args[2], out seconds)))
        {
            Console.Error.WriteLine("usage: mono ScriptedSession.exe ws://HOST:PORT SHAPE [SECONDS]");
            return 2;
        }
        try
        {
            var seen = Run(new Uri(args[0]), args[1], seconds).GetAwaiter().GetResult();
            Console.WriteLine(Json.Write(seen));
            bool ok = (string)seen["malformed_error"] == "malformed" && (string)seen["out_of_order_error"] == "out_of_order"
                && seen.ContainsKey("pens_redirected") && (int)seen["pens_redirected"] == (int)seen["pens_sent"];
            return ok ? 0 : 1;
        }
        catch (Exception e)
        {
            Console.Error.WriteLine("scripted session failed: " + e.Message);
            return 1;
        }
    }
}
